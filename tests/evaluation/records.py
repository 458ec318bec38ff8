"""Hand-made evaluation records for the tests of the summaries and reports."""

from __future__ import annotations

import math
from typing import Any

from tools.evaluation.metrics import QueryRecord


def hand_made(
    config: str = "c",
    query: str = "q",
    pos: float = math.inf,
    rot: float = math.inf,
    localized: bool | None = None,
    **fields: Any,
) -> QueryRecord:
    """A record of ``query`` under ``config``, ``pos`` metres and ``rot`` degrees off; it is
    localized when the errors are finite unless ``localized`` says otherwise; ``fields`` set
    the rest (``confidence``, ``reason``, ``estimator_used``, ``unrelated``, ...)."""
    if localized is None:
        localized = math.isfinite(pos)
    return QueryRecord(
        config=config,
        query=query,
        localized=localized,
        reason=fields.pop("reason", None if localized else "no_consensus"),
        position_error_m=pos,
        rotation_error_deg=rot,
        num_inliers=0,
        confidence=fields.pop("confidence", 0.0),
        timings_ms={},
        retrieved=[],
        cam_from_world=None,
        **fields,
    )
