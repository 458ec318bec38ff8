"""Where a map is weak: its references on their ground plane, cell by cell, with its latest
self-evaluation's held-out answers and its queries' outcomes
(``services.self_evaluation.coverage``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from app.usecases.maps import require_map
from db.repositories.evaluations import EvaluationRepository
from db.repositories.images import ImageRepository
from services.capture.spacing import map_spacing
from services.errors import InvalidInputError
from services.self_evaluation.coverage import CELL_SPACINGS, Coverage, HeldOut, coverage

# the most cells an answer may hold (a bounded cost whatever cell size is asked)
MAX_CELLS = 20_000
# the smallest default cell (a map of one place)
MIN_CELL_M = 0.05


@dataclass(frozen=True)
class MapCoverage:
    """The map's coverage, and the evaluation it read (None: the map has no finished one)."""

    coverage: Coverage
    evaluation_id: str | None


def map_coverage(
    sessions: sessionmaker[Session], map_id: str, cell_m: float | None = None
) -> MapCoverage:
    """The map's cells at ``cell_m`` (None: ``CELL_SPACINGS`` × the map's spacing).

    Raises:
        NotFoundError: unknown map.
        InvalidInputError: ``cell_m`` would cut the map into more than ``MAX_CELLS`` cells.
    """
    with sessions() as session:
        require_map(session, map_id)
        images = ImageRepository(session)
        poses = images.poses(map_id)
        outcomes = images.query_outcomes(map_id)
        evaluation = EvaluationRepository(session).latest_done(map_id)
        result: dict[str, Any] = dict(evaluation.result or {}) if evaluation is not None else {}
        evaluation_id = evaluation.id if evaluation is not None else None
    index = {image_id: k for k, image_id in enumerate(poses)}
    centers = np.array([pose.center for pose in poses.values()]).reshape(-1, 3)
    if cell_m is None:
        spacing = map_spacing(centers)
        cell_m = max(CELL_SPACINGS * spacing if spacing else MIN_CELL_M, MIN_CELL_M)
    elif len(centers):
        extent = np.ptp(centers, axis=0)
        if math.prod(float(e) / cell_m + 1 for e in sorted(extent)[1:]) > MAX_CELLS:
            raise InvalidInputError(
                f"cell_m: {cell_m:g} cuts the map into more than {MAX_CELLS} cells; ask for "
                "larger cells"
            )
    held_out = []
    configurations: dict[str, Any] = result.get("configurations") or {}
    measured: dict[str, Any] = configurations.get(str(result.get("served"))) or {}
    for answer in measured.get("references") or []:
        k = index.get(str(answer.get("image_id")))
        if k is not None:
            held_out.append(
                HeldOut(
                    k,
                    bool(answer.get("localized")),
                    _number(answer.get("position_error_m")),
                    _number(answer.get("rotation_error_deg")),
                )
            )
    queries = {index[i]: counts for i, counts in outcomes.items() if i in index}
    return MapCoverage(coverage(centers, held_out, cell_m, queries), evaluation_id)


def _number(value: object) -> float:
    """A stored error (None or absent: a failure, infinite)."""
    return float(value) if isinstance(value, int | float) else math.inf
