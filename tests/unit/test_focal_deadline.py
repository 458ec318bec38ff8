"""Issue "Holds under every fault", N3: the focal estimation of a query without a camera
keeps the request's time budget (its leave-one-reference-out jackknife refits once per
reference: 30 references take seconds unbounded)."""

from __future__ import annotations

import pytest

from services.confidence.model import default_confidence_model
from services.estimators.base import FailureReason
from services.estimators.focal import estimate_focal
from services.estimators.ransac import Deadline
from services.estimators.registry import get_estimator
from services.geometry.camera import default_camera
from services.localization.estimate import answer_pose
from tests.estimators.conftest import TEST_OPTIONS
from tests.timing import timed
from tools.synthetic.correspondences import SyntheticCorrespondences, make_correspondences

BUDGET_S = 0.3
# the steps between two deadline checks (a triangulation, a RANSAC fit) on a loaded machine
SLACK_S = 0.5


@pytest.fixture(scope="module")
def many_references() -> SyntheticCorrespondences:
    return make_correspondences(seed=3, num_references=30)


def test_focal_estimation_stops_at_the_deadline(
    many_references: SyntheticCorrespondences,
) -> None:
    elapsed, found = timed(
        lambda: estimate_focal(
            640, 480, many_references.references, TEST_OPTIONS, Deadline(BUDGET_S)
        ),
        BUDGET_S + SLACK_S,
    )
    assert found.camera is None
    assert found.failure_reason is FailureReason.TIME_BUDGET_EXCEEDED
    assert elapsed < BUDGET_S + SLACK_S, elapsed


def test_a_spent_budget_stops_focal_estimation_at_once(
    many_references: SyntheticCorrespondences,
) -> None:
    elapsed, found = timed(
        lambda: estimate_focal(640, 480, many_references.references, TEST_OPTIONS, Deadline(0.0)),
        SLACK_S,
    )
    assert found.failure_reason is FailureReason.TIME_BUDGET_EXCEEDED
    assert elapsed < SLACK_S


def test_a_query_without_camera_out_of_time_answers_time_budget_exceeded(
    many_references: SyntheticCorrespondences,
) -> None:
    """The answer names the spent budget, not an unobservable focal length."""
    answer = answer_pose(
        get_estimator("auto"),
        default_camera(640, 480),
        True,
        many_references.references,
        TEST_OPTIONS,
        Deadline(0.0),
        default_confidence_model(),
    )
    assert answer.camera is None
    assert answer.result.failure_reason is FailureReason.TIME_BUDGET_EXCEEDED
