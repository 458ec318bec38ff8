"""The engine's ``ReferenceStore`` backed by the database (one map, one feature model)."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from db.arrays import from_row
from db.models import FeatureArray, ReferenceImage
from services.features.base import LocalFeatures
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.pipeline import ReferenceView, RetrievalIndex


def camera_of(row: ReferenceImage) -> Camera:
    return Camera(row.camera_model, row.width, row.height, tuple(row.camera_params))


def pose_of(row: ReferenceImage) -> Rigid3d:
    return Rigid3d.from_quaternion(
        np.array([row.qw, row.qx, row.qy, row.qz]), np.array([row.tx, row.ty, row.tz])
    )


class SqlReferenceStore:
    """Reads the references of ``map_id`` whose features were made by ``feature_model`` and
    ``descriptor_model``; each call runs in its own short read transaction."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        map_id: str,
        feature_model: str,
        descriptor_model: str,
    ) -> None:
        self.sessions = sessions
        self.map_id = map_id
        self.feature_model = feature_model
        self.descriptor_model = descriptor_model

    def retrieval_index(self) -> RetrievalIndex:
        stmt = (
            select(ReferenceImage, FeatureArray)
            .join(FeatureArray, FeatureArray.image_id == ReferenceImage.id)
            .where(
                ReferenceImage.map_id == self.map_id,
                ReferenceImage.feature_model == self.feature_model,
                ReferenceImage.descriptor_model == self.descriptor_model,
                FeatureArray.kind == "global_descriptor",
            )
            .order_by(ReferenceImage.id)
        )
        with self.sessions() as session:
            rows = session.execute(stmt).all()
        if not rows:
            return RetrievalIndex([], np.zeros((0, 1), np.float32), np.zeros((0, 3)))
        return RetrievalIndex(
            image_ids=[image.id for image, _ in rows],
            descriptors=np.stack([from_row(array) for _, array in rows]).astype(np.float32),
            centers=np.stack([pose_of(image).center for image, _ in rows]),
        )

    def load_references(self, image_ids: list[str]) -> list[ReferenceView]:
        if not image_ids:
            return []
        with self.sessions() as session:
            images = {
                row.id: row
                for row in session.scalars(
                    select(ReferenceImage).where(
                        ReferenceImage.id.in_(image_ids), ReferenceImage.map_id == self.map_id
                    )
                )
            }
            arrays: dict[str, dict[str, np.ndarray]] = defaultdict(dict)
            for row in session.scalars(
                select(FeatureArray).where(
                    FeatureArray.image_id.in_(list(images)),
                    FeatureArray.kind.in_(["keypoints", "descriptors", "scores", "depth"]),
                )
            ):
                arrays[row.image_id][row.kind] = from_row(row)
        views = []
        for image_id in image_ids:
            image = images.get(image_id)
            stored = arrays.get(image_id, {})
            if image is None or "keypoints" not in stored:  # deleted since retrieval
                continue
            depth = stored.get("depth")
            camera = camera_of(image)
            views.append(
                ReferenceView(
                    image_id=image.id,
                    name=image.name,
                    camera=camera,
                    cam_from_world=pose_of(image),
                    features=LocalFeatures(
                        stored["keypoints"].astype(np.float32),
                        stored["descriptors"].astype(np.float32),
                        stored["scores"].astype(np.float32),
                        (camera.width, camera.height),
                    ),
                    depth=depth.astype(np.float32) if depth is not None else None,
                )
            )
        return views
