"""Which answers get a second opinion, from which configuration, and what the answer becomes;
the descriptions kept between requests."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app.usecases.localize import second_configuration
from services.estimators.base import FailureReason
from services.estimators.options import RansacOptions, UncertaintyOptions
from services.estimators.uncertainty import PoseUncertainty
from services.geometry.rigid import Rigid3d
from services.localization.answer import (
    LocalizationResult,
    RetrievedReference,
    SecondOpinion,
)
from services.localization.second_opinion import DescribedCache, merged, wants_second_opinion
from services.references.store import ReferenceData

STAGES = ("decode", "extract", "retrieve", "match", "estimate", "total")
RANSAC = RansacOptions()
MAX_ITERATIONS = RANSAC.max_iterations
UNCERTAINTY = UncertaintyOptions()
MIN_CONFIDENCE = 0.3


def _result(reason: str | None, retrieved: int = 3, ms: float = 10.0) -> LocalizationResult:
    empty = np.zeros((0, 2))
    return LocalizationResult(
        localized=reason is None,
        reason=reason,
        estimator="auto",
        cam_from_world=Rigid3d.identity() if reason is None else None,
        num_inliers=100 if reason is None else 0,
        confidence=0.9 if reason is None else 0.1,
        retrieved=[
            RetrievedReference(f"id{i}", f"ref{i}", 0.5, 10, 0, empty, empty)
            for i in range(retrieved)
        ],
        timings_ms=dict.fromkeys(STAGES, ms),
        stats={},
    )


@pytest.mark.parametrize(
    "reason",
    [
        "too_few_matches",
        "no_consensus",
        "degenerate_geometry",
        "focal_unobservable",
        "low_confidence",
    ],
)
def test_a_failure_with_references_asks_a_second_opinion(reason: str) -> None:
    assert wants_second_opinion(_result(reason), RANSAC)
    assert not wants_second_opinion(_result(reason, retrieved=0), RANSAC)


@pytest.mark.parametrize("reason", ["no_consensus", "degenerate_geometry", "low_confidence"])
def test_a_pose_search_that_ran_to_its_cap_asks_none(reason: str) -> None:
    """An image of nothing in the map: no pose that a few percent of its matches agree with."""
    for iterations, asks in ((101, True), (MAX_ITERATIONS - 1, True), (MAX_ITERATIONS, False)):
        result = replace(_result(reason), stats={"iterations": float(iterations)})
        assert wants_second_opinion(result, RANSAC) is asks


@pytest.mark.parametrize(
    "reason",
    [
        None,
        FailureReason.NO_REFERENCES.value,
        FailureReason.TIME_BUDGET_EXCEEDED.value,
        FailureReason.MISSING_DEPTH.value,
        FailureReason.GRAVITY_MISMATCH.value,
    ],
)
def test_an_answer_or_an_unrelated_failure_asks_none(reason: str | None) -> None:
    assert not wants_second_opinion(_result(reason), RANSAC)


def test_the_second_configuration_is_another_served_one() -> None:
    served = ("xfeat-lg", "sift")
    assert second_configuration(served, "auto", "sift") == "xfeat-lg"
    assert second_configuration(served, "auto", "xfeat-lg") == "sift"
    assert second_configuration(("sift",), "auto", "sift") is None
    assert second_configuration(served, "sift", "xfeat-lg") == "sift"
    assert second_configuration(served, "sift", "sift") is None  # not the map's own
    assert second_configuration(served, "aliked", "sift") is None  # not served here
    assert second_configuration(served, "", "sift") is None


def test_the_answer_is_the_second_when_it_localized_and_times_add_up() -> None:
    first = _result("no_consensus", ms=10.0)
    opinion = SecondOpinion("xfeat-lg", True, None, 0.9, 25.0, 3)
    answer = merged(first, _result(None, ms=25.0), opinion, MIN_CONFIDENCE, UNCERTAINTY)
    assert answer.localized and answer.second_opinion == opinion
    assert answer.timings_ms == dict.fromkeys(STAGES, 35.0)
    failed = replace(opinion, localized=False, reason="no_consensus")
    kept = merged(first, _result("no_consensus", ms=5.0), failed, MIN_CONFIDENCE, UNCERTAINTY)
    assert not kept.localized and kept.reason == "no_consensus" and kept.second_opinion == failed
    assert kept.timings_ms["total"] == 15.0


def _withheld(
    x_m: float,
    turn_deg: float,
    confidence: float,
    position_rms_m: float = 0.02,
) -> LocalizationResult:
    """A ``low_confidence`` answer whose candidate lies ``x_m`` along x from the origin, turned
    by ``turn_deg`` about the optical axis, with an uncertainty of ``position_rms_m``."""
    angle = np.radians(turn_deg)
    rotation = np.array(
        [[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0, 0, 1]]
    )
    pose = Rigid3d(rotation, -rotation @ np.array([x_m, 0.0, 0.0]))
    uncertainty = PoseUncertainty(position_rms_m, 0.5, 40, 1.0, position_rms_m, 0.5)
    return replace(
        _result("low_confidence"),
        confidence=confidence,
        candidate=pose,
        candidate_uncertainty=uncertainty,
    )


OPINION = SecondOpinion("xfeat-lg", False, "low_confidence", 0.2, 300.0, 10)


def test_two_withheld_poses_that_agree_answer_the_more_confident() -> None:
    first, second = _withheld(0.0, 0.0, 0.1), _withheld(0.10, 2.0, 0.2)
    answer = merged(first, second, OPINION, MIN_CONFIDENCE, UNCERTAINTY)
    assert answer.localized and answer.reason is None
    assert answer.second_opinion == replace(OPINION, agreed=True)
    assert answer.cam_from_world is second.candidate and answer.candidate is None
    assert answer.uncertainty is second.candidate_uncertainty
    assert answer.confidence == pytest.approx(UNCERTAINTY.capped_confidence, abs=1e-6)
    assert answer.timings_ms["total"] == 20.0
    # the map's when it is the more confident
    mine = merged(_withheld(0.0, 0.0, 0.25), second, OPINION, MIN_CONFIDENCE, UNCERTAINTY)
    assert mine.localized and mine.cam_from_world is not None
    np.testing.assert_allclose(mine.cam_from_world.center, [0.0, 0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("x_m, turn_deg", [(0.16, 0.0), (0.0, 3.1), (1.0, 20.0)])
def test_two_withheld_poses_apart_keep_the_first(x_m: float, turn_deg: float) -> None:
    """Apart by more than 15 cm or 3° (0.6 of the confidence's 25 cm and 5°)."""
    first = _withheld(0.0, 0.0, 0.1)
    answer = merged(first, _withheld(x_m, turn_deg, 0.2), OPINION, MIN_CONFIDENCE, UNCERTAINTY)
    assert answer == replace(first, timings_ms=answer.timings_ms, second_opinion=OPINION)


def test_an_agreement_stays_withheld_below_the_requests_min_confidence() -> None:
    first, second = _withheld(0.0, 0.0, 0.1), _withheld(0.05, 1.0, 0.2)
    answer = merged(first, second, OPINION, 0.6, UNCERTAINTY)
    assert not answer.localized and answer.reason == "low_confidence"
    assert answer.second_opinion is not None and answer.second_opinion.agreed
    assert answer.confidence == pytest.approx(UNCERTAINTY.capped_confidence, abs=1e-6)
    assert answer.candidate is second.candidate and answer.cam_from_world is None


def test_an_agreement_is_not_more_confident_than_its_uncertainty_allows() -> None:
    """An uncertainty of 50 cm (RMS) leaves a chance of about 0.14 to lie within 25 cm."""
    first, second = _withheld(0.0, 0.0, 0.1, 0.5), _withheld(0.05, 1.0, 0.05, 0.5)
    answer = merged(first, second, OPINION, MIN_CONFIDENCE, UNCERTAINTY)
    assert not answer.localized and answer.second_opinion is not None
    assert answer.second_opinion.agreed
    assert 0.1 < answer.confidence < MIN_CONFIDENCE


def test_a_failure_without_a_pose_agrees_with_nothing() -> None:
    first = _result("no_consensus")
    answer = merged(first, _withheld(0.0, 0.0, 0.2), OPINION, MIN_CONFIDENCE, UNCERTAINTY)
    assert not answer.localized and answer.reason == "no_consensus"
    assert answer.second_opinion == OPINION


def _data(tag: float) -> ReferenceData:
    return ReferenceData(None, np.full(4, tag, np.float32), None, "x", "g")  # type: ignore[arg-type]


def test_the_cache_keeps_the_most_recently_used() -> None:
    cache = DescribedCache(2)
    cache.put("xfeat", "a", _data(1))
    cache.put("xfeat", "b", _data(2))
    assert cache.get("xfeat", "a") is not None  # a is now the most recent
    cache.put("xfeat", "c", _data(3))
    assert cache.get("xfeat", "b") is None
    assert cache.get("xfeat", "a") is not None and cache.get("xfeat", "c") is not None
    assert cache.get("sift", "a") is None  # by extractor
    assert len(cache) == 2
