"""The wider retrieval: only unsure answers are matched again against a wider spread of
references, each keeps the more confident of its two answers, and a wider retrieval that
brings no other reference, or a spent budget, estimates nothing again."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from services.estimators.options import RansacOptions
from services.features.base import LocalFeatures
from services.geometry.camera import default_camera
from services.localization.answer import LocalizationResult
from services.localization.clock import OutOfTimeError, StageClock
from services.localization.stages import MatchedQuery
from services.localization.widen import SURE_CONFIDENCE, sure, widen_unsure
from services.retrieval.thinning import SPACING_FACTOR, WIDER_SPACING_FACTOR, thin_references

RANSAC = RansacOptions()


def _answer(localized: bool, confidence: float, reason: str | None = None) -> LocalizationResult:
    return LocalizationResult(
        localized=localized,
        reason=reason if reason is not None or localized else "low_confidence",
        estimator="auto",
        cam_from_world=None,
        num_inliers=100,
        confidence=confidence,
        retrieved=[],
        timings_ms={},
        stats={},
    )


def _matched(turn: int = 0) -> MatchedQuery:
    features = LocalFeatures(
        keypoints=np.zeros((0, 2), np.float32),
        descriptors=np.zeros((0, 64), np.float32),
        scores=np.zeros(0, np.float32),
        image_size=(640, 480),
    )
    return MatchedQuery(default_camera(640, 480), [], {}, turn, features)


def test_only_unsure_answers_are_estimated_again_and_keep_the_more_confident() -> None:
    results = [
        _answer(True, 0.9),  # sure: kept as it is
        _answer(True, 0.2),  # unsure: the wider answer is more confident
        _answer(True, 0.3),  # unsure: the wider answer is less confident
        _answer(False, 0.0),  # no pose: any localized answer is better
    ]
    wider_answers = {1: _answer(True, 0.7), 2: _answer(True, 0.1), 3: _answer(True, 0.95)}
    asked: list[int] = []
    upright = _matched(turn=90)
    wider = _matched(turn=90)

    def match_wider(matched: MatchedQuery) -> MatchedQuery:
        assert matched is upright
        return wider

    def estimate(i: int, matched: MatchedQuery) -> LocalizationResult:
        assert matched is wider
        asked.append(i)
        return wider_answers[i]

    widened, ran = widen_unsure(results, upright, match_wider, estimate, StageClock(None), RANSAC)
    assert ran == [False, True, True, True]  # each answer: estimated on the wider match
    assert asked == [1, 2, 3]
    assert [r.confidence for r in widened] == [0.9, 0.7, 0.3, 0.95]


def test_sure_answers_match_nothing_again() -> None:
    def match_wider(_: MatchedQuery) -> MatchedQuery:
        raise AssertionError("a sure answer was matched again")

    results = [_answer(True, SURE_CONFIDENCE), _answer(False, 0.0, reason="missing_depth")]
    widened, ran = widen_unsure(results, _matched(), match_wider, _never, StageClock(None), RANSAC)
    assert ran == [False, False]
    assert widened == results
    assert sure(results[0], RANSAC) and sure(results[1], RANSAC)
    assert not sure(_answer(True, SURE_CONFIDENCE - 0.01), RANSAC)


def test_a_pose_search_that_found_nothing_is_not_widened() -> None:
    """An answer whose pose search drew every hypothesis without a pose (an image of nothing
    in the map) is not matched again; one that stopped earlier is."""
    cap = float(RANSAC.max_iterations)
    in_vain = replace(_answer(False, 0.0, reason="no_consensus"), stats={"iterations": cap})
    searched = replace(in_vain, stats={"iterations": cap - 1})
    assert sure(in_vain, RANSAC) and not sure(searched, RANSAC)
    widened, ran = widen_unsure(
        [in_vain, searched], _matched(), lambda m: m, lambda i, m: in_vain, StageClock(None), RANSAC
    )
    assert ran == [False, True]
    assert widened[0] is in_vain


def test_no_other_reference_or_no_time_left_estimates_nothing_again() -> None:
    results = [_answer(True, 0.2)]
    for match_wider in (lambda _: None, _out_of_time):
        widened, ran = widen_unsure(
            results, _matched(), match_wider, _never, StageClock(None), RANSAC
        )
        assert ran == [False]
        assert widened == results
    spent = StageClock(0.0)
    widened, ran = widen_unsure(results, _matched(), _out_of_time, _never, spent, RANSAC)
    assert ran == [False]


def test_the_wider_spacing_keeps_references_farther_apart() -> None:
    # a capture along x, 25 cm between frames, ranked best first from the query's end
    centers = np.stack([np.arange(30) * 0.25, np.zeros(30), np.zeros(30)], axis=1)
    rows = np.arange(30, dtype=np.int64)
    scores = np.linspace(1.0, 0.5, 30).astype(np.float32)
    close, _ = thin_references(rows, scores, centers, k=5)
    wide, _ = thin_references(rows, scores, centers, k=5, spacing_factor=WIDER_SPACING_FACTOR)
    assert SPACING_FACTOR < WIDER_SPACING_FACTOR
    np.testing.assert_array_equal(close, [0, 2, 4, 6, 8])
    np.testing.assert_array_equal(wide, [0, 3, 6, 9, 12])


def _never(_: int, __: MatchedQuery) -> LocalizationResult:
    raise AssertionError("estimated again")


def _out_of_time(_: MatchedQuery) -> MatchedQuery:
    raise OutOfTimeError
