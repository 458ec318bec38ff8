"""Queries on maps."""

from __future__ import annotations

from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session

from db.models import Map, ReferenceImage, is_stored_id


def lock_map_row(session: Session, map_id: str) -> None:
    """Lock the map row first: every writer of a map's images takes the map row, then the
    images, then their arrays (as a vocabulary publish does), so two writers wait for each
    other instead of deadlocking."""
    session.execute(select(Map.id).where(Map.id == map_id).with_for_update(key_share=True))


class MapRepository:
    def __init__(self, session: Session) -> None:
        self.session = session

    def create(
        self,
        name: str,
        description: str | None,
        default_estimator: str | None = None,
        max_keypoints: int | None = None,
        max_side: int | None = None,
        feature_preset: str | None = None,
        features_auto: bool = True,
        grow_from_queries: bool = False,
        retire_stale: bool = False,
    ) -> Map:
        """A new map, flushed; ``default_estimator`` None takes the column's default;
        ``feature_preset`` None serves it with the server's configuration until
        (``features_auto``) its self-evaluation recommends one."""
        row = Map(
            name=name,
            description=description,
            default_estimator=default_estimator,
            max_keypoints=max_keypoints,
            max_side=max_side,
            feature_preset=feature_preset,
            features_auto=features_auto,
            grow_from_queries=grow_from_queries,
            retire_stale=retire_stale,
        )
        self.session.add(row)
        self.session.flush()
        return row

    def get(self, map_id: str) -> Map | None:
        if not is_stored_id(map_id):
            return None
        return self.session.get(Map, map_id)

    def get_by_name(self, name: str) -> Map | None:
        return self.session.scalars(select(Map).where(Map.name == name)).one_or_none()

    def page(self, offset: int, limit: int) -> tuple[list[Map], int]:
        total = self.session.scalar(select(func.count()).select_from(Map)) or 0
        rows = self.session.scalars(
            select(Map).order_by(Map.created_at, Map.id).offset(offset).limit(limit)
        ).all()
        return list(rows), total

    def image_counts(self, map_ids: list[str]) -> dict[str, int]:
        if not map_ids:
            return {}
        rows = self.session.execute(
            select(ReferenceImage.map_id, func.count())
            .where(ReferenceImage.map_id.in_(map_ids))
            .group_by(ReferenceImage.map_id)
        ).all()
        return {map_id: int(count) for map_id, count in rows}

    def without_original_counts(self, map_ids: list[str]) -> dict[str, int]:
        """Per map, its images stored without their originals (added before they were
        kept)."""
        if not map_ids:
            return {}
        rows = self.session.execute(
            select(ReferenceImage.map_id, func.count())
            .where(ReferenceImage.map_id.in_(map_ids), ReferenceImage.original_key.is_(None))
            .group_by(ReferenceImage.map_id)
        ).all()
        return {map_id: int(count) for map_id, count in rows}

    def described_by(
        self, map_ids: list[str] | None = None
    ) -> dict[str, list[tuple[str, str, int]]]:
        """Per map (of ``map_ids``, None: every map), the ``(feature model, descriptor model,
        image count)`` its references were described by, most images first."""
        stmt = select(
            ReferenceImage.map_id,
            ReferenceImage.feature_model,
            ReferenceImage.descriptor_model,
            func.count(),
        ).group_by(
            ReferenceImage.map_id, ReferenceImage.feature_model, ReferenceImage.descriptor_model
        )
        if map_ids is not None:
            if not map_ids:
                return {}
            stmt = stmt.where(ReferenceImage.map_id.in_(map_ids))
        out: dict[str, list[tuple[str, str, int]]] = {}
        for map_id, feature_model, descriptor_model, count in self.session.execute(stmt):
            out.setdefault(map_id, []).append((feature_model, descriptor_model, int(count)))
        for groups in out.values():
            groups.sort(key=lambda g: (-g[2], g[0], g[1]))
        return out

    def largest(self, limit: int) -> list[tuple[str, str, int]]:
        """``(id, name, image count)`` of the ``limit`` maps with the most images, largest
        first."""
        count = func.count(ReferenceImage.id)
        rows = self.session.execute(
            select(Map.id, Map.name, count)
            .outerjoin(ReferenceImage, ReferenceImage.map_id == Map.id)
            .group_by(Map.id, Map.name)
            .order_by(count.desc(), Map.id)
            .limit(limit)
        ).all()
        return [(map_id, name, int(n)) for map_id, name, n in rows]

    def delete(self, map_id: str) -> bool:
        """Delete a map with its images and their features. True when it existed."""
        # ON DELETE CASCADE does the work on both backends; the explicit statement keeps the
        # result independent of ORM state.
        if not is_stored_id(map_id):
            return False
        result = self.session.execute(delete(Map).where(Map.id == map_id))
        return bool(result.rowcount)  # type: ignore[attr-defined]
