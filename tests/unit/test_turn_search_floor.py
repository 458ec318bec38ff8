"""When the search over quarter turns stops for an answer: once it is confident, or once it
has so many inliers that the query was matched the right way up (a wrongly turned query
localizes with none: ``services.pipeline.UPRIGHT_INLIERS``)."""

from __future__ import annotations

import pytest

from services.pipeline import SEARCH_CONFIDENCE, UPRIGHT_INLIERS, LocalizationResult, _settled


def _answer(localized: bool, confidence: float, inliers: int) -> LocalizationResult:
    return LocalizationResult(
        localized=localized,
        reason=None if localized else "no_consensus",
        estimator="e5p1",
        cam_from_world=None,
        num_inliers=inliers,
        confidence=confidence,
        retrieved=[],
        timings_ms={},
        stats={},
    )


@pytest.mark.parametrize(
    ("localized", "confidence", "inliers", "settled"),
    [
        (True, SEARCH_CONFIDENCE, 10, True),  # confident: nothing to search
        (True, 0.3, UPRIGHT_INLIERS, True),  # unsure, but matched upright
        (True, 0.3, UPRIGHT_INLIERS - 1, False),  # unsure with few inliers: try the turns
        (False, 0.0, 5000, False),  # no pose: try the turns
    ],
)
def test_search_stops_for_confident_or_well_matched_answers(
    localized: bool, confidence: float, inliers: int, settled: bool
) -> None:
    assert _settled(_answer(localized, confidence, inliers)) is settled
