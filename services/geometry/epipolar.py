"""Epipolar distances of correspondences under known poses (match-quality measurements)."""

from __future__ import annotations

import numpy as np

from services.geometry.camera import Camera
from services.geometry.depth_pose import skew
from services.geometry.rigid import Rigid3d
from services.types import FloatArray


def epipolar_errors(
    camera_a: Camera,
    a_from_world: Rigid3d,
    xy_a: FloatArray,
    camera_b: Camera,
    b_from_world: Rigid3d,
    xy_b: FloatArray,
) -> FloatArray:
    """(N,) symmetric point-to-epipolar-line distances in pixels of matches ``xy_a`` ↔ ``xy_b``
    ((N, 2) COLMAP pixels), the mean of the distance in image a and in image b. Pinhole
    intrinsics (distortion ignored)."""
    b_from_a = b_from_world.compose(a_from_world.inverse())
    essential = skew(b_from_a.translation) @ b_from_a.rotation
    fundamental = np.linalg.inv(camera_b.K).T @ essential @ np.linalg.inv(camera_a.K)
    pa = np.column_stack([xy_a, np.ones(len(xy_a))])
    pb = np.column_stack([xy_b, np.ones(len(xy_b))])
    lines_b, lines_a = pa @ fundamental.T, pb @ fundamental
    residual = np.abs(np.sum(pb * lines_b, axis=1))
    distance_b = residual / np.maximum(np.hypot(lines_b[:, 0], lines_b[:, 1]), 1e-12)
    distance_a = residual / np.maximum(np.hypot(lines_a[:, 0], lines_a[:, 1]), 1e-12)
    errors: FloatArray = 0.5 * (distance_a + distance_b)
    return errors
