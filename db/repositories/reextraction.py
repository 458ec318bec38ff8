"""Queries of a map's re-description: references are described anew from their originals
into staged arrays (kinds ``next:…``) while the map keeps serving its current ones, then the
map switches to the staged descriptions in one transaction."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import ColumnElement, delete, func, or_, select, update
from sqlalchemy.orm import Session

from db.arrays import to_row
from db.models import FeatureArray, Map, ReferenceImage
from db.repositories.maps import lock_map_row
from db.vocabulary import VLAD_KIND
from services.references.store import ReferenceData

STAGED = "next:"
# the arrays a description replaces; depth comes from the upload, not the extractor, and stays
DESCRIBED_KINDS = ("keypoints", "descriptors", "scores", "global_descriptor")


@dataclass(frozen=True)
class Progress:
    """References of a map described for its pending options (``described``) of those that
    can be (``total``: the references with their originals)."""

    described: int
    total: int


class ReextractionRepository:
    def __init__(self, session: Session) -> None:
        self.session = session

    def maps_pending(self) -> list[str]:
        """The maps whose references are being re-described, oldest first."""
        return list(
            self.session.scalars(
                select(Map.id).where(Map.reextracting.is_(True)).order_by(Map.created_at)
            )
        )

    def start(
        self, map_id: str, preset: str | None, max_keypoints: int | None, max_side: int | None
    ) -> None:
        """Sets the map's pending configuration and options (flushed, not committed);
        descriptions staged for others are described again, those staged for these are
        kept."""
        lock_map_row(self.session, map_id)
        self.session.execute(
            update(Map)
            .where(Map.id == map_id)
            .values(
                reextracting=True,
                pending_preset=preset,
                pending_max_keypoints=max_keypoints,
                pending_max_side=max_side,
            )
        )

    def cancel(self, map_id: str) -> None:
        """No options pending: the staged descriptions are dropped."""
        lock_map_row(self.session, map_id)
        self.session.execute(
            update(Map)
            .where(Map.id == map_id)
            .values(
                reextracting=False,
                pending_preset=None,
                pending_max_keypoints=None,
                pending_max_side=None,
            )
        )
        self._drop_staged(map_id)

    def to_describe(self, map_id: str, target_model: str, limit: int) -> list[ReferenceImage]:
        """Up to ``limit`` references with originals described otherwise, without a staged
        description of ``target_model``."""
        return list(
            self.session.scalars(
                select(ReferenceImage)
                .where(
                    *self._redescribed(map_id, target_model),
                    ReferenceImage.original_key.is_not(None),
                    or_(
                        ReferenceImage.next_feature_model.is_(None),
                        ReferenceImage.next_feature_model != target_model,
                    ),
                )
                .order_by(ReferenceImage.id)
                .limit(limit)
            )
        )

    def stage(self, map_id: str, image_id: str, data: ReferenceData) -> bool:
        """Stores ``data`` as the reference's staged description (flushed, not committed);
        False when the reference is gone."""
        lock_map_row(self.session, map_id)
        row = self.session.get(ReferenceImage, image_id)
        if row is None or row.map_id != map_id:
            return False
        self.session.execute(
            delete(FeatureArray).where(
                FeatureArray.image_id == image_id, FeatureArray.kind.startswith(STAGED)
            )
        )
        arrays = {
            "keypoints": data.features.keypoints,
            "descriptors": data.features.descriptors,
            "scores": data.features.scores,
            "global_descriptor": data.global_descriptor,
        }
        self.session.add_all(
            to_row(image_id, STAGED + kind, array) for kind, array in arrays.items()
        )
        row.next_feature_model = data.feature_model
        self.session.flush()
        return True

    def progress(self, map_id: str, target_model: str) -> Progress:
        """How far the map's re-description for ``target_model`` has come, over the
        references another description serves now that have their originals."""
        described = func.count().filter(ReferenceImage.next_feature_model == target_model)
        row = self.session.execute(
            select(func.count(), described).where(
                *self._redescribed(map_id, target_model), ReferenceImage.original_key.is_not(None)
            )
        ).one()
        return Progress(int(row[1]), int(row[0]))

    def without_original(self, map_id: str, target_model: str) -> int:
        """The references that would need describing for ``target_model`` but have no
        original to be described from."""
        return int(
            self.session.scalar(
                select(func.count()).where(
                    *self._redescribed(map_id, target_model), ReferenceImage.original_key.is_(None)
                )
            )
            or 0
        )

    @staticmethod
    def _redescribed(map_id: str, target_model: str) -> tuple[ColumnElement[bool], ...]:
        return (ReferenceImage.map_id == map_id, ReferenceImage.feature_model != target_model)

    def switch(self, map_id: str, target_model: str, descriptor_model: str) -> int:
        """The map serves its staged descriptions of ``target_model`` from now on: each
        staged reference's arrays replace its current ones (its VLAD vector is dropped, a
        new vocabulary encodes it), the pending configuration and options become the map's
        and its revision
        moves. References that could not be described (no original) keep their old
        description, which the map no longer serves. Returns the references switched."""
        lock_map_row(self.session, map_id)
        staged = select(ReferenceImage.id).where(
            ReferenceImage.map_id == map_id, ReferenceImage.next_feature_model == target_model
        )
        self.session.execute(
            delete(FeatureArray).where(
                FeatureArray.image_id.in_(staged),
                FeatureArray.kind.in_([*DESCRIBED_KINDS, VLAD_KIND]),
            )
        )
        for kind in DESCRIBED_KINDS:
            self.session.execute(
                update(FeatureArray)
                .where(FeatureArray.image_id.in_(staged), FeatureArray.kind == STAGED + kind)
                .values(kind=kind)
                .execution_options(synchronize_session=False)
            )
        ids = list(self.session.scalars(staged))
        shapes = dict(
            self.session.execute(
                select(FeatureArray.image_id, FeatureArray.shape).where(
                    FeatureArray.image_id.in_(ids), FeatureArray.kind == "keypoints"
                )
            ).all()
        )
        for row in self.session.scalars(select(ReferenceImage).where(ReferenceImage.id.in_(ids))):
            row.num_keypoints = int(shapes[row.id][0])
            row.feature_model = target_model
            row.descriptor_model = descriptor_model
            row.vlad_version = None
            row.next_feature_model = None
        map_row = self.session.get(Map, map_id)
        assert map_row is not None  # locked above
        map_row.feature_preset = map_row.pending_preset
        map_row.max_keypoints = map_row.pending_max_keypoints
        map_row.max_side = map_row.pending_max_side
        map_row.reextracting = False
        map_row.pending_preset = None
        map_row.pending_max_keypoints = map_row.pending_max_side = None
        map_row.revision += 1
        self._drop_staged(map_id)
        self.session.flush()
        return len(ids)

    def _drop_staged(self, map_id: str) -> None:
        images = select(ReferenceImage.id).where(ReferenceImage.map_id == map_id)
        self.session.execute(
            delete(FeatureArray).where(
                FeatureArray.image_id.in_(images), FeatureArray.kind.startswith(STAGED)
            )
        )
        self.session.execute(
            update(ReferenceImage)
            .where(ReferenceImage.map_id == map_id, ReferenceImage.next_feature_model.is_not(None))
            .values(next_feature_model=None)
        )
