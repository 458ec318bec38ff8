"""Geometry building blocks of the estimators: averaging, ray intersection, triangulation,
tracks, and the world-frame Sampson error."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.estimators.base import ReferenceObservation
from services.estimators.correspondences import (
    pose_sampson_errors_px,
    random_subset,
    stack_matches,
    unique_points,
)
from services.estimators.options import EstimatorOptions
from services.estimators.pose_triangulation import sampled_solver, solve_5pt
from services.estimators.ransac import Deadline
from services.estimators.tracks import build_tracks
from services.geometry import triangulation as geometry_triangulation
from services.geometry.averaging import (
    average_rotations,
    irls_ray_intersection,
    ransac_ray_intersection,
)
from services.geometry.camera import Camera
from services.geometry.depth_pose import sampson_errors
from services.geometry.rigid import Rigid3d, rotation_error_deg
from services.geometry.triangulation import (
    ransac_triangulate,
    triangulate_dlt,
    triangulate_pairs,
)
from tools.synthetic.correspondences import make_correspondences


def test_rotation_averaging_rejects_outliers() -> None:
    rng = np.random.default_rng(0)
    truth = np.asarray(cv2.Rodrigues(np.array([0.3, -0.2, 0.1]))[0], dtype=np.float64)
    noisy = [cv2.Rodrigues(rng.normal(0, 0.002, 3))[0] @ truth for _ in range(7)]
    wild = [cv2.Rodrigues(rng.normal(0, 1.0, 3))[0] @ truth for _ in range(3)]
    R, inliers = average_rotations(np.stack(noisy + wild), np.ones(10), 5.0)
    assert rotation_error_deg(R, truth) < 0.3
    assert inliers[:7].all() and not inliers[7:].any()


def test_ray_intersection_exact_and_robust() -> None:
    rng = np.random.default_rng(1)
    point = np.array([0.5, -0.2, 1.0])
    origins = rng.uniform(-3, 3, (8, 3))
    directions = point - origins
    directions[6:] = rng.normal(size=(2, 3))  # outlier rays
    for solve in (ransac_ray_intersection, irls_ray_intersection):
        found, inliers, cond = solve(origins, directions, np.ones(8), 5.0)
        assert np.linalg.norm(found - point) < 1e-9
        assert inliers[:6].all() and not inliers[6:].any() and cond > 1e-3


def test_ray_intersection_degenerate_when_parallel() -> None:
    origins = np.array([[0.0, 0, 0], [0, 0, 0], [0, 0, 0]])
    directions = np.array([[1.0, 0, 0], [1, 0, 0], [1, 0, 0]])
    found, _, _ = ransac_ray_intersection(origins, directions, np.ones(3), 5.0)
    assert not np.all(np.isfinite(found))


def _views(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    Rs = np.stack([cv2.Rodrigues(rng.normal(0, 0.1, 3))[0] for _ in range(n)])
    centers = rng.uniform([-1, -1, -1], [1, 1, 0], (n, 3))
    P = np.concatenate([Rs, -(Rs @ centers[:, :, None])], axis=2)
    return P, centers


def test_triangulation_exact_and_ransac() -> None:
    rng = np.random.default_rng(2)
    P, centers = _views(rng, 5)
    X = rng.uniform([-2, -2, 4], [2, 2, 8], (100, 3))
    Xc = np.einsum("vij,tj->tvi", P[:, :, :3], X) + P[:, :, 3]
    obs = Xc[..., :2] / Xc[..., 2:]
    np.testing.assert_allclose(triangulate_dlt(obs, P, np.ones((100, 5))), X, atol=1e-8)
    corrupted = obs.copy()
    corrupted[:, 4] += 0.2  # view 4 is an outlier in every track
    observed = np.ones((100, 5), dtype=bool)
    observed[:10, 3] = False
    tri = ransac_triangulate(corrupted, observed, P, np.full(5, 500.0), centers, 2.0)
    np.testing.assert_allclose(tri.points, X, atol=1e-8)
    assert tri.valid.all() and not tri.inliers[:, 4].any()
    assert not tri.inliers[:10, 3].any() and tri.inliers[10:, 3].all()


def test_two_view_triangulation_against_the_dlt(monkeypatch: pytest.MonkeyPatch) -> None:
    """``triangulate_pairs`` recovers exact points, agrees with the DLT's null vector to a
    small fraction of the points' own error under noise, and leaves parallel rays
    non-finite; the RANSAC's winning hypothesis is the first pair with the most inliers, and
    chunks of pairs choose as one pass over them does."""
    rng = np.random.default_rng(5)
    P, _ = _views(rng, 2)
    X = rng.uniform([-2, -2, 4], [2, 2, 8], (200, 3))
    Xc = np.einsum("vij,tj->tvi", P[:, :, :3], X) + P[:, :, 3]
    obs = Xc[..., :2] / Xc[..., 2:]
    pairs = np.broadcast_to(P, (200, 2, 3, 4))
    np.testing.assert_allclose(triangulate_pairs(obs, pairs), X, atol=1e-9)
    noisy = obs + rng.normal(0.0, 1e-3, obs.shape)  # 0.5 px at f = 500
    linear = triangulate_pairs(noisy, pairs)
    dlt = triangulate_dlt(noisy, P, np.ones((200, 2)))
    gap = np.linalg.norm(linear - dlt, axis=1)
    error = np.linalg.norm(dlt - X, axis=1)
    assert np.median(gap) < 0.05 * np.median(error)
    same_ray = np.stack([np.eye(3, 4), np.eye(3, 4)])
    assert not np.isfinite(triangulate_pairs(np.zeros((1, 2, 2)), same_ray[None])).all()

    P5, centers5 = _views(rng, 5)
    X5 = rng.uniform([-2, -2, 4], [2, 2, 8], (60, 3))
    Xc5 = np.einsum("vij,tj->tvi", P5[:, :, :3], X5) + P5[:, :, 3]
    obs5 = Xc5[..., :2] / Xc5[..., 2:] + rng.normal(0.0, 2e-3, (60, 5, 2))
    observed = rng.random((60, 5)) < 0.8
    whole = ransac_triangulate(obs5, observed, P5, np.full(5, 500.0), centers5, 2.0)
    monkeypatch.setattr(geometry_triangulation, "HYPOTHESIS_CHUNK_ENTRIES", 1)  # a pair a chunk
    single = ransac_triangulate(obs5, observed, P5, np.full(5, 500.0), centers5, 2.0)
    np.testing.assert_array_equal(whole.points, single.points)
    np.testing.assert_array_equal(whole.inliers, single.inliers)


def test_tracks_group_shared_query_keypoints() -> None:
    cam = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
    q = np.array([[10.0, 10.0], [20.0, 20.0], [30.0, 30.0]])
    refs = [
        ReferenceObservation("a", cam, Rigid3d.identity(), q[[0, 1]], q[[0, 1]]),
        ReferenceObservation("b", cam, Rigid3d.identity(), q[[1, 2]], q[[1, 2]]),
    ]
    tracks = build_tracks(stack_matches(cam, refs))
    assert tracks.size == 3
    np.testing.assert_array_equal(tracks.observed.sum(axis=1), [1, 2, 1])
    merged = build_tracks(stack_matches(cam, refs), merge_px=100.0)
    assert merged.size == 1


def test_unique_points_is_numpys_row_unique() -> None:
    """Distinct rows, first occurrences and each row's index as ``np.unique(axis=0)`` gives
    them, on keypoints shared across references (repeats, equal x with different y)."""
    rng = np.random.default_rng(5)
    keypoints = np.round(rng.uniform(0.5, 640.5, (300, 2)), 2)
    keypoints[:40, 0] = keypoints[40:80, 0]  # same x, another y
    xy = keypoints[rng.integers(0, 300, 2000)]
    points, first, inverse = unique_points(xy)
    expected, expected_first, expected_inverse = np.unique(
        xy, axis=0, return_index=True, return_inverse=True
    )
    np.testing.assert_array_equal(points, expected)
    np.testing.assert_array_equal(first, expected_first)
    np.testing.assert_array_equal(inverse, expected_inverse.reshape(-1))
    np.testing.assert_array_equal(points[inverse], xy)


def test_world_frame_sampson_matches_pairwise_sampson() -> None:
    data = make_correspondences(seed=3, num_references=3, matches_per_reference=50)
    stacked = stack_matches(data.query_camera, data.references)
    pose = data.query_pose
    world = pose_sampson_errors_px(stacked, pose.rotation[None], pose.center[None])[0]
    for i, ref in enumerate(data.references):
        rel = pose.compose(ref.cam_from_world.inverse())
        sl = slice(stacked.offsets[i], stacked.offsets[i + 1])
        pair = sampson_errors(
            rel.rotation[None], rel.translation[None], stacked.ref_norm[sl], stacked.query_norm[sl]
        )[0]
        np.testing.assert_allclose(world[sl], pair * 500.0, rtol=1e-8, atol=1e-9)


def test_sampled_solver_scores_every_match() -> None:
    """RANSAC on a 100-match sample returns a proposal of the pair's pose (robust averaging
    refines it later) and an inlier mask over all its matches that agrees with the truth."""
    scene = make_correspondences(seed=5, num_references=2, matches_per_reference=1000)
    ref, truth = scene.references[0], scene.inlier_masks[0]
    options = EstimatorOptions()
    pair = sampled_solver(solve_5pt, 100)(
        ref, scene.query_camera, options, Deadline(None), 1, np.random.default_rng(0)
    )
    assert pair is not None and pair.inliers.shape == (ref.num_matches,)
    expected = scene.query_pose.compose(ref.cam_from_world.inverse())
    assert rotation_error_deg(pair.query_from_ref.rotation, expected.rotation) < 2.5
    agree = (pair.inliers == truth).mean()
    assert agree > 0.97, agree


def test_random_subset() -> None:
    rng = np.random.default_rng(0)
    assert np.array_equal(random_subset(5, 10, rng), np.arange(5))
    picked = random_subset(1000, 100, rng)
    assert picked.shape == (100,) and np.unique(picked).size == 100
    assert np.all(np.diff(picked) > 0) and picked.max() < 1000
