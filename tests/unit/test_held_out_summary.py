"""The self-evaluation's sample, held-out maps, summaries and recommendation, on layouts and
answers whose outcome is known."""

from __future__ import annotations

import math

import numpy as np

from services.self_evaluation.sample import held_out_map, spread_sample
from services.self_evaluation.summary import HeldOutAnswer, recommend, summarize


def _line(n: int) -> np.ndarray:
    """Camera centres 1 m apart along x."""
    return np.stack([np.arange(n, dtype=np.float64), np.zeros(n), np.zeros(n)], axis=1)


def test_the_sample_spreads_from_the_middle_to_the_ends() -> None:
    sample = spread_sample(_line(11), 3)
    assert sample.tolist() == [5, 0, 10]  # the middle, then the farthest, then the other end
    # then the first of the points farthest from those (2, 3, 7, 8 tie at 2 m), and so on
    assert sorted(spread_sample(_line(11), 5).tolist()) == [0, 2, 5, 7, 10]
    assert sorted(spread_sample(_line(4), 10).tolist()) == [0, 1, 2, 3]  # all, when asked more


def test_the_held_out_map_is_the_nearest_beyond_the_radius() -> None:
    centers = _line(10)
    assert held_out_map(centers, 5, 3, 0.0).tolist() == [4, 6, 3]
    # within 2 m of the held-out reference: 3, 4, 6, 7 go with it
    assert held_out_map(centers, 5, 3, 2.0).tolist() == [2, 8, 1]
    assert held_out_map(centers, 0, 100, 0.0).tolist() == list(range(1, 10))
    assert held_out_map(centers, 0, 100, 1000.0).tolist() == []


def _answer(
    error_m: float | None, confidence: float = 0.9, latency: float = 100.0
) -> HeldOutAnswer:
    localized = error_m is not None
    return HeldOutAnswer(
        image_id="i",
        name="n",
        localized=localized,
        reason=None if localized else "no_consensus",
        position_error_m=error_m if localized else math.inf,
        rotation_error_deg=0.5 if localized else math.inf,
        confidence=confidence if localized else 0.0,
        num_inliers=100 if localized else 0,
        latency_ms=latency,
    )


def test_summary_counts_failures_as_infinite_errors() -> None:
    answers = [_answer(0.01), _answer(0.03), _answer(0.2, confidence=0.5), _answer(None)]
    summary = summarize(answers)
    assert summary["held_out"] == 4 and summary["localized"] == 3
    assert summary["recall"] == {"5cm_5deg": 0.5, "10cm_10deg": 0.5, "25cm_2deg": 0.75}
    assert summary["position_error_m"] == {"median": 0.03, "p90": None}  # p90 is a failure
    assert summary["failures"] == {"no_consensus": 1}
    # two answers above 0.8, both right; three right answers in all
    assert summary["confidence"]["precision"] == 1.0
    assert summary["confidence"]["recall"] == 2 / 3
    assert summarize([])["position_error_m"] == {"median": None, "p90": None}


def test_the_recommendation_is_the_fastest_close_to_the_best() -> None:
    accurate = summarize([_answer(0.010, latency=900.0)] * 10)
    close = summarize([_answer(0.0108, latency=200.0)] * 10)
    fast_but_coarse = summarize([_answer(0.030, latency=100.0)] * 10)
    failing = summarize([_answer(0.010, latency=50.0)] * 5 + [_answer(None)] * 5)
    summaries = {"a": accurate, "b": close, "c": fast_but_coarse, "d": failing}
    assert recommend(summaries) == "b"  # c's median is 3x the best, d misses half
    # within 10 % of the best median, millimetres or not: 1.5 mm is not close to 1.0 mm
    coarser = summarize([_answer(0.0015, latency=100.0)] * 10)
    finer = summarize([_answer(0.0010, latency=120.0)] * 10)
    assert recommend({"x": coarser, "s": finer}, current="x") == "s"
    assert recommend({"a": accurate}) == "a"
    assert recommend({"x": summarize([_answer(None)] * 3)}) is None
    # a map keeps its configuration while it is close to the best and about as fast as the
    # fastest of those (within 10 %)
    about_as_fast = summarize([_answer(0.0105, latency=215.0)] * 10)
    assert recommend({**summaries, "e": about_as_fast}, current="e") == "e"
    assert recommend(summaries, current="a") == "b"  # 4.5x slower: moves on
    assert recommend(summaries, current="c") == "b"  # not close to the best: moves on


def test_the_recommendation_weighs_recall_before_the_median() -> None:
    """A configuration with the best median but a recall more than 5 points below the best
    is out, and the median is compared among those left; when each configuration is best at
    another threshold, the best mean recall stays in: the rule always names one."""
    precise = summarize([_answer(0.010, latency=100.0)] * 8 + [_answer(None)] * 2)
    complete = summarize([_answer(0.014, latency=300.0)] * 10)
    assert recommend({"precise": precise, "complete": complete}) == "complete"
    # (5 cm, 5°): a 90 %, b 80 %; (25 cm, 2°): a 90 %, b 100 %: neither within 5 points of
    # the best at both; a's mean recall is the higher (0.9 against 0.87)
    a = summarize([_answer(0.02)] * 9 + [_answer(None)])
    b = summarize([_answer(0.02)] * 8 + [_answer(0.2)] * 2)
    assert recommend({"a": a, "b": b}) == "a"
