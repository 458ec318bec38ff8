"""Queries of maps' self-evaluations."""

from __future__ import annotations

from datetime import UTC, datetime

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from db.models import MapEvaluation, ReferenceImage

# an evaluation in one of these states has not finished
ACTIVE = ("queued", "running")


class EvaluationRepository:
    def __init__(self, session: Session) -> None:
        self.session = session

    def create(self, map_id: str, request: dict[str, object]) -> MapEvaluation:
        row = MapEvaluation(map_id=map_id, state="queued", request=request, done=0, total=0)
        self.session.add(row)
        self.session.flush()
        return row

    def get(self, map_id: str, evaluation_id: str) -> MapEvaluation | None:
        row = self.session.get(MapEvaluation, evaluation_id)
        return row if row is not None and row.map_id == map_id else None

    def page(self, map_id: str, offset: int, limit: int) -> tuple[list[MapEvaluation], int]:
        """The map's evaluations, newest first, and how many it has."""
        rows = self.session.scalars(
            select(MapEvaluation)
            .where(MapEvaluation.map_id == map_id)
            .order_by(MapEvaluation.created_at.desc(), MapEvaluation.id)
            .offset(offset)
            .limit(limit)
        )
        total = self.session.scalar(
            select(func.count()).select_from(MapEvaluation).where(MapEvaluation.map_id == map_id)
        )
        return list(rows), int(total or 0)

    def evaluating(self, map_ids: list[str]) -> set[str]:
        """Those of the maps with an evaluation queued or running."""
        if not map_ids:
            return set()
        return set(
            self.session.scalars(
                select(MapEvaluation.map_id).where(
                    MapEvaluation.map_id.in_(map_ids), MapEvaluation.state.in_(ACTIVE)
                )
            )
        )

    def active(self, map_id: str) -> MapEvaluation | None:
        """The map's evaluation still queued or running, if any."""
        return self.session.scalar(
            select(MapEvaluation).where(
                MapEvaluation.map_id == map_id, MapEvaluation.state.in_(ACTIVE)
            )
        )

    def latest_done(self, map_id: str) -> MapEvaluation | None:
        return self.session.scalar(
            select(MapEvaluation)
            .where(MapEvaluation.map_id == map_id, MapEvaluation.state == "done")
            .order_by(MapEvaluation.finished_at.desc())
            .limit(1)
        )

    def unfinished(self) -> list[str]:
        """Ids of the evaluations a restart interrupted (queued or running), oldest first."""
        return list(
            self.session.scalars(
                select(MapEvaluation.id)
                .where(MapEvaluation.state.in_(ACTIVE))
                .order_by(MapEvaluation.created_at)
            )
        )

    def references(self, map_id: str) -> list[ReferenceImage]:
        """The map's references that have their original, in a stable order."""
        return list(
            self.session.scalars(
                select(ReferenceImage)
                .where(ReferenceImage.map_id == map_id, ReferenceImage.original_key.is_not(None))
                .order_by(ReferenceImage.name)
            )
        )

    def reference_count(self, map_id: str) -> int:
        """How many of the map's references have their original."""
        return int(
            self.session.scalar(
                select(func.count()).where(
                    ReferenceImage.map_id == map_id, ReferenceImage.original_key.is_not(None)
                )
            )
            or 0
        )

    def latest(self, map_id: str) -> MapEvaluation | None:
        """The map's most recent evaluation, whatever its state."""
        return self.session.scalar(
            select(MapEvaluation)
            .where(MapEvaluation.map_id == map_id)
            .order_by(MapEvaluation.created_at.desc(), MapEvaluation.id)
            .limit(1)
        )

    def set_state(self, evaluation_id: str, state: str, **values: object) -> bool:
        """Moves an unfinished evaluation to ``state`` with ``values``; False when it is
        finished already (or gone)."""
        now = datetime.now(UTC)
        if state == "running":
            values.setdefault("started_at", now)
        elif state not in ACTIVE:
            values.setdefault("finished_at", now)
        updated = self.session.execute(
            update(MapEvaluation)
            .where(MapEvaluation.id == evaluation_id, MapEvaluation.state.in_(ACTIVE))
            .values(state=state, **values)
        )
        return bool(getattr(updated, "rowcount", 0))
