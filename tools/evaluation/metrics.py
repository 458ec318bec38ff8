"""Per-query records and per-configuration summaries: recall at (metres, degrees)
thresholds, error percentiles, failures by reason, stage timings, and the ground-truth facts
that explain failures (was a reference close enough? did retrieval find one?)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from services.geometry.rigid import Rigid3d, pose_error
from services.self_evaluation.summary import THRESHOLDS, recall_key
from services.types import BoolArray, FloatArray

if TYPE_CHECKING:  # the runner needs the `eval` extra (httpx); the CLI reads these names without it
    from tools.evaluation.runner import QueryOutcome

# the thresholds a map's self-evaluation reports too
DEFAULT_THRESHOLDS = THRESHOLDS
# a query is "localizable" when a reference lies within 0.3 m and 15° (ground truth); its
# retrieval "hits" when a retrieved reference lies within 0.5 m and 30°
LOCALIZABLE = (0.3, 15.0)
RETRIEVAL_NEAR = (0.5, 30.0)
STAGES = ("decode", "extract", "retrieve", "match", "estimate", "total", "client")


@dataclass
class QueryRecord:
    """One query localized under one configuration (``features/estimator``).

    Errors are ``inf`` without a pose; ``unrelated`` queries (images of nothing in the map)
    have no ground truth and count as false accepts when localized. ``candidate_*_error``:
    the errors of a ``low_confidence`` answer's withheld pose (``inf`` without one).
    """

    config: str
    query: str
    localized: bool
    reason: str | None
    position_error_m: float
    rotation_error_deg: float
    num_inliers: int
    confidence: float
    timings_ms: dict[str, float]
    retrieved: list[str]
    cam_from_world: dict[str, list[float]] | None
    localizable: bool = False
    retrieval_covered: bool = False
    retrieval_hit: bool = False
    unrelated: bool = False
    wrong_intrinsics: bool = False
    stats: dict[str, float] = field(default_factory=dict)
    estimator_used: str | None = None
    candidate_position_error_m: float = float("inf")
    candidate_rotation_error_deg: float = float("inf")


@dataclass(frozen=True)
class ReferencePoses:
    """Ground-truth poses of the map's references, for the neighbour facts of a query."""

    names: list[str]
    centers: FloatArray  # (N, 3)
    rotations: FloatArray  # (N, 3, 3) cam_from_world

    @classmethod
    def of(cls, poses: dict[str, Rigid3d]) -> ReferencePoses:
        names = list(poses)
        return cls(
            names,
            np.array([poses[n].center for n in names]).reshape(-1, 3),
            np.array([poses[n].rotation for n in names]).reshape(-1, 3, 3),
        )

    def near(self, truth: Rigid3d, max_m: float, max_deg: float) -> BoolArray:
        """(N,) references within ``max_m`` metres and ``max_deg`` degrees of ``truth``."""
        dist = np.linalg.norm(self.centers - truth.center, axis=1)
        rel = self.rotations @ truth.rotation.T
        cos = (np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0
        angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        near: BoolArray = (dist <= max_m) & (angle <= max_deg)
        return near


def make_record(
    config: str,
    query: str,
    outcome: QueryOutcome,
    truth: Rigid3d | None,
    references: ReferencePoses,
) -> QueryRecord:
    """``truth`` None marks an unrelated image."""
    pose = outcome.cam_from_world
    pos_err = rot_err = float("inf")
    if truth is not None and pose is not None:
        pos_err, rot_err = pose_error(pose.to_rigid(), truth)
    candidate_pos_err = candidate_rot_err = float("inf")
    if truth is not None and outcome.candidate is not None:
        candidate_pos_err, candidate_rot_err = pose_error(outcome.candidate.to_rigid(), truth)
    record = QueryRecord(
        config=config,
        query=query,
        localized=outcome.localized,
        reason=outcome.reason,
        position_error_m=pos_err,
        rotation_error_deg=rot_err,
        num_inliers=outcome.num_inliers,
        confidence=outcome.confidence,
        timings_ms=outcome.timings_ms,
        retrieved=outcome.retrieved,
        estimator_used=outcome.estimator_used,
        cam_from_world=pose.model_dump() if pose is not None else None,
        unrelated=truth is None,
        stats=outcome.stats,
        candidate_position_error_m=candidate_pos_err,
        candidate_rotation_error_deg=candidate_rot_err,
    )
    if truth is not None:
        record.localizable = bool(references.near(truth, *LOCALIZABLE).any())
        near = references.near(truth, *RETRIEVAL_NEAR)
        record.retrieval_covered = bool(near.any())
        near_names = {n for n, ok in zip(references.names, near, strict=True) if ok}
        record.retrieval_hit = any(name in near_names for name in outcome.retrieved)
    return record


def within(record: QueryRecord, max_m: float, max_deg: float) -> bool:
    """The record's pose lies within ``max_m`` and ``max_deg`` of the truth (a failure's
    errors are infinite: never)."""
    return record.position_error_m <= max_m and record.rotation_error_deg <= max_deg


def _quantile(ordered: FloatArray, q: float) -> float:
    """Linear-interpolated quantile of sorted values; where the upper neighbour is a
    failure's inf, the lower order statistic (interpolating towards inf means nothing)."""
    position = (len(ordered) - 1) * q
    lo, hi = ordered[int(np.floor(position))], ordered[int(np.ceil(position))]
    if lo == hi or not np.isfinite(hi):
        return float(lo)
    return float(lo + (hi - lo) * (position - np.floor(position)))


def _percentiles(values: list[float]) -> dict[str, float]:
    if not values:
        return {"median": float("nan"), "p90": float("nan")}
    ordered = np.sort(np.asarray(values, np.float64))
    return {"median": _quantile(ordered, 0.5), "p90": _quantile(ordered, 0.9)}


# an answer above this confidence should be right within these errors (issue 12)
CONFIDENT = 0.8
WRONG_M, WRONG_DEG = 0.25, 5.0


def confident_answers(posed: list[QueryRecord]) -> dict[str, int]:
    """``confident``: localized answers with confidence above ``CONFIDENT``;
    ``confident_wrong``: those more than ``WRONG_M`` or ``WRONG_DEG`` off."""
    confident = [r for r in posed if r.localized and r.confidence > CONFIDENT]
    wrong = [r for r in confident if not within(r, WRONG_M, WRONG_DEG)]
    return {"confident": len(confident), "confident_wrong": len(wrong)}


def withheld_answers(posed: list[QueryRecord]) -> dict[str, int]:
    """``withheld``: answers whose pose fell below ``min_confidence`` (``low_confidence``,
    the pose as their candidate); ``withheld_right``: those of them within ``WRONG_M`` and
    ``WRONG_DEG``, the right answers the threshold turned away."""
    withheld = [r for r in posed if r.reason == "low_confidence"]
    right = [
        r
        for r in withheld
        if r.candidate_position_error_m <= WRONG_M and r.candidate_rotation_error_deg <= WRONG_DEG
    ]
    return {"withheld": len(withheld), "withheld_right": len(right)}


def second_opinions(posed: list[QueryRecord]) -> dict[str, Any]:
    """The queries a second configuration localized again (in process, ``--second-opinion``):
    ``second_opinions`` asked, ``second_opinions_localized`` of them answered by it, and
    those within ``WRONG_M`` and ``WRONG_DEG`` (``second_opinions_right``); those whose
    withheld pose agreed with the map's (``second_opinions_agreed``), the queries localized
    so (``agreed_localized``) and those of them within ``WRONG_M`` and ``WRONG_DEG``
    (``agreed_right``); their median time (``second_opinion_ms``, null when none was
    asked)."""
    asked = [r for r in posed if "second_opinion_ms" in r.stats]
    localized = [r for r in asked if r.stats.get("second_opinion_localized", 0.0) > 0.0]
    agreed = [r for r in asked if r.stats.get("second_opinion_agreed", 0.0) > 0.0]
    agreed_localized = [r for r in agreed if r.localized]
    return {
        "second_opinions": len(asked),
        "second_opinions_localized": len(localized),
        "second_opinions_right": sum(within(r, WRONG_M, WRONG_DEG) for r in localized),
        "second_opinions_agreed": len(agreed),
        "agreed_localized": len(agreed_localized),
        "agreed_right": sum(within(r, WRONG_M, WRONG_DEG) for r in agreed_localized),
        "second_opinion_ms": float(np.median([r.stats["second_opinion_ms"] for r in asked]))
        if asked
        else None,
    }


def choices(
    posed: list[QueryRecord], thresholds: tuple[tuple[float, float], ...]
) -> dict[str, dict[str, Any]]:
    """The localized answers by the estimator whose pose each is (``auto`` names its choice;
    any other answers as itself), most answers first: their count and the share of them
    within each threshold."""
    by_used: dict[str, list[QueryRecord]] = {}
    for r in posed:
        if r.localized:
            by_used.setdefault(r.estimator_used or r.config.rsplit("/", 1)[-1], []).append(r)
    return {
        name: {
            "answers": len(answers),
            "recall": {
                recall_key(m, d): sum(within(r, m, d) for r in answers) / len(answers)
                for m, d in thresholds
            },
        }
        for name, answers in sorted(by_used.items(), key=lambda item: -len(item[1]))
    }


def summarize(
    records: list[QueryRecord], thresholds: tuple[tuple[float, float], ...]
) -> dict[str, Any]:
    """Summary of one configuration's records (queries with ground truth; unrelated images
    and queries sent with wrong intrinsics are counted apart)."""
    posed = [r for r in records if not r.unrelated and not r.wrong_intrinsics]
    unrelated = [r for r in records if r.unrelated]
    wrong_intrinsics = [r for r in records if r.wrong_intrinsics]
    pos = np.array([r.position_error_m for r in posed])
    rot = np.array([r.rotation_error_deg for r in posed])
    n = len(posed)
    easy = [r for r in posed if r.localizable]
    covered = [r for r in posed if r.retrieval_covered]
    lm, ld = 0.10, 5.0
    return {
        "queries": n,
        "localized": sum(r.localized for r in posed),
        "recall": {
            recall_key(m, d): float(((pos <= m) & (rot <= d)).mean()) if n else 0.0
            for m, d in thresholds
        },
        "position_error_m": _percentiles(pos.tolist()),
        "rotation_error_deg": _percentiles(rot.tolist()),
        "failures": dict(Counter(r.reason or "unknown" for r in posed if not r.localized)),
        "choices": choices(posed, thresholds),
        "timings_ms": {
            stage: _percentiles([r.timings_ms[stage] for r in records if stage in r.timings_ms])
            for stage in STAGES
        },
        "localizable_queries": len(easy),
        "localizable_recall_10cm_5deg": (
            sum(within(r, lm, ld) for r in easy) / len(easy) if easy else 0.0
        ),
        "retrieval_covered_queries": len(covered),
        "retrieval_recall": sum(r.retrieval_hit for r in covered) / len(covered)
        if covered
        else 0.0,
        **confident_answers(posed),
        **withheld_answers(posed),
        **second_opinions(posed),
        "unrelated_queries": len(unrelated),
        "unrelated_accepted": sum(r.localized for r in unrelated),
        "wrong_intrinsics_queries": len(wrong_intrinsics),
        "wrong_intrinsics_accepted": sum(r.localized for r in wrong_intrinsics),
    }
