"""Queries on reference images and their feature arrays."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from sqlalchemy import Table, bindparam, delete, func, select, update
from sqlalchemy.orm import Session

from db.arrays import to_row
from db.models import FeatureArray, Map, ReferenceImage, ReferencePreview, is_stored_id
from db.originals import StoredOriginals
from db.repositories.maps import lock_map_row
from services.geo.gps import GpsFix
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.imaging.preview import Preview
from services.references.store import ReferenceData


class ImageRepository:
    def __init__(self, session: Session) -> None:
        self.session = session

    def add(
        self,
        map_id: str,
        name: str,
        camera: Camera,
        cam_from_world: Rigid3d,
        data: ReferenceData,
        gps: GpsFix | None = None,
        image_id: str | None = None,
        originals: StoredOriginals | None = None,
    ) -> ReferenceImage:
        """Insert the image row and all its arrays (flushed, not committed). ``image_id``:
        the row's id (None: a new one); ``originals``: where its originals were written."""
        lock_map_row(self.session, map_id)
        qw, qx, qy, qz = (float(v) for v in cam_from_world.quaternion)
        tx, ty, tz = (float(v) for v in cam_from_world.translation)
        row = ReferenceImage(
            map_id=map_id,
            original_key=originals.original_key if originals else None,
            original_sha256=originals.original_sha256 if originals else None,
            depth_key=originals.depth_key if originals else None,
            name=name,
            camera_model=camera.model,
            width=camera.width,
            height=camera.height,
            camera_params=[float(p) for p in camera.params],
            qw=qw,
            qx=qx,
            qy=qy,
            qz=qz,
            tx=tx,
            ty=ty,
            tz=tz,
            num_keypoints=len(data.features),
            has_depth=data.depth is not None,
            feature_model=data.feature_model,
            descriptor_model=data.descriptor_model,
            gps_latitude=gps.latitude if gps else None,
            gps_longitude=gps.longitude if gps else None,
            gps_height=gps.height if gps else None,
            gps_accuracy_m=gps.accuracy_m if gps else None,
        )
        if image_id is not None:
            row.id = image_id
        self.session.add(row)
        self.session.flush()
        arrays = {
            "keypoints": data.features.keypoints,
            "descriptors": data.features.descriptors,
            "scores": data.features.scores,
            "global_descriptor": data.global_descriptor,
        }
        if data.depth is not None:
            arrays["depth"] = data.depth.astype("float16")
        self.session.add_all(to_row(row.id, kind, array) for kind, array in arrays.items())
        self._bump_revision(map_id)
        self.session.flush()
        return row

    def with_gps(self, map_id: str) -> list[ReferenceImage]:
        """The map's images that carry a GPS position, oldest first."""
        return list(
            self.session.scalars(
                select(ReferenceImage)
                .where(
                    ReferenceImage.map_id == map_id,
                    ReferenceImage.gps_latitude.is_not(None),
                    ReferenceImage.gps_longitude.is_not(None),
                )
                .order_by(ReferenceImage.created_at, ReferenceImage.id)
            )
        )

    def add_preview(self, image_id: str, preview: Preview) -> None:
        self.session.add(
            ReferencePreview(
                image_id=image_id, width=preview.width, height=preview.height, jpeg=preview.jpeg
            )
        )
        self.session.flush()

    def preview(self, map_id: str, image_id: str) -> Preview | None:
        """The image's preview; None for an unknown image or one stored without a preview."""
        if not (is_stored_id(map_id) and is_stored_id(image_id)):
            return None
        row = self.session.scalars(
            select(ReferencePreview)
            .join(ReferenceImage, ReferenceImage.id == ReferencePreview.image_id)
            .where(ReferencePreview.image_id == image_id, ReferenceImage.map_id == map_id)
        ).one_or_none()
        return None if row is None else Preview(row.jpeg, row.width, row.height)

    def get(self, map_id: str, image_id: str) -> ReferenceImage | None:
        if not (is_stored_id(map_id) and is_stored_id(image_id)):
            return None
        return self.session.scalars(
            select(ReferenceImage).where(
                ReferenceImage.id == image_id, ReferenceImage.map_id == map_id
            )
        ).one_or_none()

    def name_exists(self, map_id: str, name: str) -> bool:
        return (
            self.session.scalar(
                select(ReferenceImage.id).where(
                    ReferenceImage.map_id == map_id, ReferenceImage.name == name
                )
            )
            is not None
        )

    def names(self, map_id: str) -> set[str]:
        return set(
            self.session.scalars(
                select(ReferenceImage.name).where(ReferenceImage.map_id == map_id)
            ).all()
        )

    def feature_models(self) -> set[str]:
        """The extractors that described the references of every map."""
        return set(self.session.scalars(select(ReferenceImage.feature_model).distinct()).all())

    def page(
        self, map_id: str, offset: int, limit: int, stale: bool | None = None
    ) -> tuple[list[ReferenceImage], int]:
        """A page of the map's images, oldest first (``stale``: only those flagged stale, or
        only those not), and how many there are."""
        where = ReferenceImage.map_id == map_id
        if stale is not None:
            flagged = ReferenceImage.stale_since.is_not(None)
            where = where & (flagged if stale else ~flagged)
        total = self.session.scalar(select(func.count()).select_from(ReferenceImage).where(where))
        rows = self.session.scalars(
            select(ReferenceImage)
            .where(where)
            .order_by(ReferenceImage.created_at, ReferenceImage.id)
            .offset(offset)
            .limit(limit)
        ).all()
        return list(rows), int(total or 0)

    def add_query_outcomes(self, counts: Mapping[str, tuple[int, int]]) -> None:
        """Adds (localized, failed) query counts to the references by id (a reference deleted
        meanwhile is skipped)."""
        table = ReferenceImage.__table__
        assert isinstance(table, Table)
        statement = (
            update(table)
            .where(table.c.id == bindparam("image_id"))
            .values(
                queries_localized=table.c.queries_localized + bindparam("localized"),
                queries_failed=table.c.queries_failed + bindparam("failed"),
            )
        )
        rows = [
            {"image_id": image_id, "localized": localized, "failed": failed}
            for image_id, (localized, failed) in counts.items()
        ]
        if rows:
            self.session.connection().execute(statement, rows)

    def query_outcomes(self, map_id: str) -> dict[str, tuple[int, int]]:
        """(localized, failed) query counts of the references that have any, by id."""
        rows = self.session.execute(
            select(
                ReferenceImage.id, ReferenceImage.queries_localized, ReferenceImage.queries_failed
            ).where(
                ReferenceImage.map_id == map_id,
                (ReferenceImage.queries_localized > 0) | (ReferenceImage.queries_failed > 0),
            )
        )
        return {image_id: (int(ok), int(failed)) for image_id, ok, failed in rows}

    def poses(self, map_id: str) -> dict[str, Rigid3d]:
        """Every image's ``cam_from_world`` by id, in id order."""
        rows = self.session.execute(
            select(
                ReferenceImage.id,
                ReferenceImage.qw,
                ReferenceImage.qx,
                ReferenceImage.qy,
                ReferenceImage.qz,
                ReferenceImage.tx,
                ReferenceImage.ty,
                ReferenceImage.tz,
            )
            .where(ReferenceImage.map_id == map_id)
            .order_by(ReferenceImage.id)
        )
        return {
            str(r[0]): Rigid3d.from_quaternion(np.array(r[1:5]), np.array(r[5:8])) for r in rows
        }

    def blob_keys(self, map_id: str, image_id: str | None = None) -> list[str]:
        """The blob keys of the map's images (of ``image_id`` alone when given)."""
        if not is_stored_id(map_id) or (image_id is not None and not is_stored_id(image_id)):
            return []
        stmt = select(ReferenceImage.original_key, ReferenceImage.depth_key).where(
            ReferenceImage.map_id == map_id
        )
        if image_id is not None:
            stmt = stmt.where(ReferenceImage.id == image_id)
        return [key for row in self.session.execute(stmt) for key in row if key is not None]

    def delete(self, map_id: str, image_id: str) -> bool:
        """Delete an image and its feature arrays. True when it existed."""
        if not (is_stored_id(map_id) and is_stored_id(image_id)):
            return False
        lock_map_row(self.session, map_id)
        result = self.session.execute(
            delete(ReferenceImage).where(
                ReferenceImage.id == image_id, ReferenceImage.map_id == map_id
            )
        )
        deleted = bool(result.rowcount)  # type: ignore[attr-defined]
        if deleted:
            self._bump_revision(map_id)
        return deleted

    def _bump_revision(self, map_id: str) -> None:
        self.session.execute(update(Map).where(Map.id == map_id).values(revision=Map.revision + 1))

    def count_orphan_arrays(self) -> int:
        """Feature arrays whose image no longer exists (0 in a healthy database)."""
        orphan = (
            ~select(ReferenceImage.id).where(ReferenceImage.id == FeatureArray.image_id).exists()
        )
        return int(
            self.session.scalar(select(func.count()).select_from(FeatureArray).where(orphan)) or 0
        )
