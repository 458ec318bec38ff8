"""When the search over quarter turns stops for an answer: once it is confident, once it
has so many inliers that the query was matched the right way up (a wrongly turned query
localizes with none: ``services.localization.turns.UPRIGHT_INLIERS``) at a confidence that does
not read it as wrong, or when it failed for want of depth, which no turn brings; and the stage
timings of several estimators over several turns."""

from __future__ import annotations

import pytest

from services.localization.answer import DEFAULT_MIN_CONFIDENCE, LocalizationResult
from services.localization.compare import own_timings
from services.localization.turns import SEARCH_CONFIDENCE, UPRIGHT_INLIERS, settled


def _answer(
    localized: bool, confidence: float, inliers: int, reason: str = "no_consensus"
) -> LocalizationResult:
    return LocalizationResult(
        localized=localized,
        reason=None if localized else reason,
        estimator="e5p1",
        cam_from_world=None,
        num_inliers=inliers,
        confidence=confidence,
        retrieved=[],
        timings_ms={},
        stats={},
    )


@pytest.mark.parametrize(
    ("localized", "confidence", "inliers", "expected"),
    [
        (True, SEARCH_CONFIDENCE, 10, True),  # confident: nothing to search
        (True, DEFAULT_MIN_CONFIDENCE, UPRIGHT_INLIERS, True),  # unsure, but matched upright
        (True, DEFAULT_MIN_CONFIDENCE, UPRIGHT_INLIERS - 1, False),  # few inliers: try turns
        (True, 1e-5, 280, False),  # a chance pose of a wrong turn: try the others
        (False, 0.0, 5000, False),  # no pose: try the turns
    ],
)
def test_search_stops_for_confident_or_well_matched_answers(
    localized: bool, confidence: float, inliers: int, expected: bool
) -> None:
    assert settled(_answer(localized, confidence, inliers)) is expected


def test_a_failure_for_want_of_depth_is_settled() -> None:
    assert settled(_answer(False, 0.0, 0, reason="missing_depth"))
    assert not settled(_answer(False, 0.0, 0, reason="too_few_matches"))


def test_an_estimators_timings_leave_the_others_estimation_out() -> None:
    summed = {"decode": 1.0, "extract": 10.0, "retrieve": 2.0, "match": 20.0}
    summed |= {"estimate": 30.0, "total": 64.0}  # 1 ms between the stages
    own = own_timings(summed, 12.0)
    assert own == {**summed, "estimate": 12.0, "total": 46.0}
