"""The own batched DLT triangulation against pycolmap's, on synthetic exact observations."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap

from services.geometry.triangulation import triangulate_dlt


def _scene(
    rng: np.random.Generator, views: int, points: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(V, 3, 4) ``cam_from_world``, (T, 3) world points in front of every view and their
    (T, V, 2) exact normalised observations."""
    R = np.stack([cv2.Rodrigues(rng.normal(0, 0.1, 3))[0] for _ in range(views)])
    centers = rng.uniform([-1, -1, -1], [1, 1, 0], (views, 3))
    P = np.concatenate([R, -(R @ centers[:, :, None])], axis=2)
    X = rng.uniform([-2, -2, 4], [2, 2, 8], (points, 3))
    X_cam = np.einsum("vij,tj->tvi", P[:, :, :3], X) + P[:, :, 3]
    return P, X, X_cam[..., :2] / X_cam[..., 2:]


def _point(found: np.ndarray | None) -> np.ndarray:
    assert found is not None
    return found.ravel()


class TestTriangulateDltAgainstPycolmap:
    def test_two_views(self) -> None:
        P, X, normalized = _scene(np.random.default_rng(0), 2, 200)
        own = triangulate_dlt(normalized, P, np.ones((200, 2)))
        colmap = np.stack(
            [_point(pycolmap.triangulate_point(P[0], P[1], x[0], x[1])) for x in normalized]
        )
        np.testing.assert_allclose(own, X, atol=1e-9)
        np.testing.assert_allclose(own, colmap, atol=1e-9)

    def test_views_chosen_per_point_by_the_weights(self) -> None:
        rng = np.random.default_rng(1)
        P, X, normalized = _scene(rng, 6, 200)
        chosen = rng.random((200, 6)) < 0.5
        chosen[:, :2] = True
        own = triangulate_dlt(normalized, P, chosen.astype(np.float64))
        rays = np.concatenate([normalized, np.ones((200, 6, 1))], axis=2)
        rays /= np.linalg.norm(rays, axis=2, keepdims=True)  # pycolmap takes unit bearings
        colmap = np.stack(
            [
                _point(pycolmap.triangulate_multi_view_point(list(P[views]), rays[t, views]))
                for t, views in enumerate(chosen)
            ]
        )
        np.testing.assert_allclose(own, X, atol=1e-9)
        np.testing.assert_allclose(own, colmap, atol=1e-9)
