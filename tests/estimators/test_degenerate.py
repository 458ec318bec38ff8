"""Singular and non-finite numerics end in a failure reason, never an exception: the
estimator template turns a singular system into ``degenerate_geometry``, and the batched
geometry primitives answer NaN for a non-finite input instead of failing to converge."""

from __future__ import annotations

import numpy as np
import pytest

from services.estimators.base import FailureReason
from services.estimators.estimator import Estimator, Request
from services.estimators.registry import estimator_names, get_estimator
from services.geometry.averaging import intersect_rays, project_to_rotation
from services.geometry.depth_pose import similarity_from_points
from services.geometry.triangulation import triangulate_dlt
from tests.estimators.conftest import TEST_OPTIONS
from tools.synthetic.correspondences import SyntheticCorrespondences


@pytest.mark.parametrize(
    "name", [n for n in estimator_names() if isinstance(get_estimator(n), Estimator)]
)
def test_singular_system_is_degenerate_geometry(
    name: str, scene: SyntheticCorrespondences, monkeypatch: pytest.MonkeyPatch
) -> None:
    estimator = get_estimator(name)
    assert isinstance(estimator, Estimator)

    def singular(self: Estimator, request: Request) -> None:
        request.stats["iterations"] = 1.0
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(type(estimator), "solve", singular)
    result = estimator.estimate(scene.query_camera, scene.references, TEST_OPTIONS)
    assert result.cam_from_world is None
    assert result.failure_reason is FailureReason.DEGENERATE_GEOMETRY
    assert result.stats == {"iterations": 1.0}
    assert [m.shape for m in result.inliers] == [(r.num_matches,) for r in scene.references]


def test_project_to_rotation_of_a_non_finite_matrix_is_nan() -> None:
    rotations = project_to_rotation(np.stack([2.0 * np.eye(3), np.full((3, 3), np.nan)]))
    np.testing.assert_allclose(rotations[0], np.eye(3))
    assert np.isnan(rotations[1]).all()


def test_similarity_of_a_non_finite_sample_is_nan() -> None:
    rng = np.random.default_rng(0)
    src = rng.random((2, 4, 3))
    dst = src + np.array([1.0, 2.0, 3.0])
    src[1, 0, 0] = np.inf
    with np.errstate(invalid="ignore"):
        R, t, s = similarity_from_points(src, dst)
    np.testing.assert_allclose(R[0], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(t[0], [1.0, 2.0, 3.0], atol=1e-12)
    assert np.isnan(R[1]).all() and np.isnan(t[1]).all() and np.isnan(s[1])


def test_triangulating_a_non_finite_track_keeps_the_others() -> None:
    point = np.array([0.3, -0.2, 5.0])
    centers = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    projections = np.stack([np.hstack([np.eye(3), -c[:, None]]) for c in centers])
    seen = point - centers
    normalized = np.stack([seen[:, :2] / seen[:, 2:], np.full((2, 2), np.nan)])
    with np.errstate(invalid="ignore"):
        points = triangulate_dlt(normalized, projections, np.ones((2, 2)))
    np.testing.assert_allclose(points[0], point, atol=1e-9)
    assert np.isfinite(points).all()  # the documented contract: NaN-free


def test_intersecting_non_finite_rays_is_degenerate() -> None:
    point, conditioning = intersect_rays(
        np.zeros((2, 3)), np.array([[0.0, 0.0, 1.0], [np.nan, 0.0, 1.0]]), np.ones(2)
    )
    assert np.isnan(point).all() and conditioning == 0.0
