"""The turn search: a query that may be sideways is matched turned upright first
(``QueryFrame.turns``, best guess first), and its other quarter turns are tried, while the
budget lasts, for the answers not settled yet; each keeps its most confident answer.

The policy's constants were measured on redkitchen (7-Scenes)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import NamedTuple

from services.estimators.base import FailureReason
from services.geometry.intrinsics_adaptation import CameraAdaptation
from services.localization.answer import DEFAULT_MIN_CONFIDENCE, LocalizationResult
from services.localization.clock import OutOfTimeError, StageClock
from services.localization.stages import MatchedQuery

SEARCH_CONFIDENCE = 0.5  # an answer below it lets the other turns of the query be tried...
# ...unless it has this many inliers. Redkitchen, 25 queries, e5p1, search off: upright, the
# localized answers had 331-3587 inliers (xfeat-lg), 288-3885 (aliked-nn), 254-3570 (sift);
# turned a quarter, none of the xfeat-lg or aliked-nn queries localized (sift, rotation
# invariant, localized 11 with 208-1622, turned or not). Before this floor, 30-52 % of the
# redkitchen queries (upright, with 224-3238 inliers) paid for up to three more turns.
UPRIGHT_INLIERS = 200
# ...and at least the default min_confidence: a turn matched the wrong way round can still
# find a pose from chance matches. The README demo's query, turned a quarter and matched with
# aliked, found one 180° off with 280 inliers at confidence 1e-5
# (tests/models/test_rotated_queries.py). On kitti05 and redkitchen (sift and xfeat-lg,
# auto, the suggested splits) no answer with 200 inliers or more was below 0.5.
# another turn is estimated only with this many times the matches of every turn estimated before
# (redkitchen, query against its best reference: XFeat 544-997 matches upright, 89-164 at the
# other turns; ALIKED 225-535 and 31-63; SIFT within 2 % at every turn)
TURN_MATCH_GAIN = 1.5


class TurnSearch(NamedTuple):
    """The answers of a turn search, how many turns were matched, and the match of the turn
    that matched most (the upright one)."""

    results: list[LocalizationResult]
    attempts: int
    upright: MatchedQuery


def search_turns(
    turns: Sequence[int],
    first: MatchedQuery,
    match: Callable[[int], MatchedQuery],
    estimate: Callable[[int, MatchedQuery], LocalizationResult],
    count: int,
    clock: StageClock,
) -> TurnSearch:
    """The answers of ``count`` estimates (``estimate(i, matched)``, i < ``count``) over the
    ``turns`` of a query, ``first`` being its match at ``turns[0]`` (``match(turn)`` matches
    another).

    The other turns are tried, while the budget lasts, for the answers not ``settled`` yet (a
    sideways image can give a pose from chance matches, which the confidence reads as
    wrong), each keeping the ``better`` of its answers. A turn is estimated only when it
    matches ``TURN_MATCH_GAIN`` times more than every turn estimated before (learned
    descriptors match a wrongly turned image 5-10x less, rotation-invariant SIFT about as
    much: estimating it again would not change the answer)."""
    results = [estimate(i, first) for i in range(count)]
    clock.lap("estimate", check=False)
    attempts = 1
    upright = first
    for turn in turns[1:]:
        if all(settled(r) for r in results) or clock.deadline.expired():
            break
        try:
            matched = match(turn)
        except OutOfTimeError:
            break
        attempts += 1
        if matched.num_matches <= TURN_MATCH_GAIN * upright.num_matches:
            continue  # no better matched than a turn already estimated: not upright
        upright = matched
        results = [
            r if settled(r) else better(r, estimate(i, matched)) for i, r in enumerate(results)
        ]
        clock.lap("estimate", check=False)
    return TurnSearch(results, attempts, upright)


def settled(result: LocalizationResult) -> bool:
    """No other turn of the query needs trying for this answer: it is confident, has so
    many inliers that the query was matched the right way up (and a confidence that does not
    read it as wrong), or failed for want of depth, which no turn brings."""
    if result.reason == FailureReason.MISSING_DEPTH.value:
        return True
    if not result.localized:
        return False
    return result.confidence >= SEARCH_CONFIDENCE or (
        result.num_inliers >= UPRIGHT_INLIERS and result.confidence >= DEFAULT_MIN_CONFIDENCE
    )


def better(a: LocalizationResult, b: LocalizationResult) -> LocalizationResult:
    """The localized one of two answers, the more confident when both are (``a`` on ties)."""
    if a.localized != b.localized:
        return a if a.localized else b
    return b if b.confidence > a.confidence else a


def searched_answer(
    result: LocalizationResult,
    attempts: int,
    widened: bool,
    adaptation: CameraAdaptation | None,
    timings_ms: dict[str, float],
    min_confidence: float,
) -> LocalizationResult:
    """The answer a search ends on: ``low_confidence`` below ``min_confidence``, with the
    camera's adaptation, the timings, the number of turns matched and whether the query was
    matched again against a wider spread of references (``services.localization.widen``)."""
    return replace(
        result.below(min_confidence),
        camera_adaptation=adaptation,
        timings_ms=timings_ms,
        stats={
            **result.stats,
            "orientation_attempts": float(attempts),
            "wider_retrieval": float(widened),
        },
    )
