"""Synthetic query–reference correspondences with exact ground truth, for estimator tests
and benchmarks (no images: points are sampled on the planes of the synthetic room and
projected with exact intrinsics).

Every query keypoint is one noisy projection of one 3D point, shared by all references that
match it (as a real detector's keypoint is), so tracks through query keypoints exist. Outliers
are wrong matches: a real query keypoint paired with a uniformly random reference pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.estimators.base import ReferenceObservation
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.types import BoolArray, FloatArray

# (origin, u, v) of the room's planes, as in ``SyntheticScene`` (x right, y down, z forward)
_PLANES = [
    ([-6, -3, 8], [12, 0, 0], [0, 6, 0]),  # back wall
    ([-6, -3, -6], [0, 0, 14], [0, 6, 0]),  # left wall
    ([6, -3, 8], [0, 0, -14], [0, 6, 0]),  # right wall
    ([-6, 3, 8], [12, 0, 0], [0, 0, -14]),  # floor
    ([-6, -3, -6], [12, 0, 0], [0, 0, 14]),  # ceiling
    ([-3.5, -1.5, 4.0], [2.5, 0, 0.5], [0, 3.5, 0]),  # panel
    ([1.2, -2.0, 5.5], [2.5, 0, -0.6], [0, 3.5, 0]),  # panel
]


@dataclass(frozen=True)
class SyntheticCorrespondences:
    """Attributes:
    query_camera, query_pose: the query's exact intrinsics and ``cam_from_world``.
    references: the observations handed to an estimator.
    scene_depth: median depth of the query's points (units of the position tolerance).
    inlier_masks: per reference, which matches are true correspondences.
    """

    query_camera: Camera
    query_pose: Rigid3d
    references: list[ReferenceObservation]
    scene_depth: float
    inlier_masks: list[BoolArray]


def _rotation(rng: np.random.Generator, base: FloatArray, max_deg: float) -> FloatArray:
    angles = np.radians(rng.uniform(-max_deg, max_deg, 3))
    return np.asarray(cv2.Rodrigues(angles)[0] @ base, dtype=np.float64)


def sample_room_points(rng: np.random.Generator, count: int) -> FloatArray:
    """(count, 3) points uniformly on the room's planes (by area)."""
    planes = [tuple(np.array(p, float) for p in plane) for plane in _PLANES]
    areas = np.array([np.linalg.norm(np.cross(u, v)) for _, u, v in planes])
    which = rng.choice(len(planes), size=count, p=areas / areas.sum())
    ab = rng.random((count, 2))
    origins = np.stack([p[0] for p in planes])[which]
    us = np.stack([p[1] for p in planes])[which]
    vs = np.stack([p[2] for p in planes])[which]
    return np.asarray(origins + ab[:, :1] * us + ab[:, 1:] * vs, dtype=np.float64)


def project_points(
    camera: Camera, pose: Rigid3d, points: FloatArray
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """(N, 3) world points → (N, 2) pixels (COLMAP convention, pinhole), (N,) z-depth and
    (N,) whether each is in front of the camera (z > 0.1) and inside the image."""
    X = pose.apply(points)
    z = X[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = X[:, :2] / z[:, None] @ camera.K[:2, :2].T + camera.K[:2, 2]
    visible = (
        (z > 0.1)
        & (xy[:, 0] > 0)
        & (xy[:, 0] < camera.width)
        & (xy[:, 1] > 0)
        & (xy[:, 1] < camera.height)
    )
    return xy, z, visible


def make_correspondences(
    seed: int = 0,
    num_references: int = 10,
    matches_per_reference: int = 300,
    noise_px: float = 1.0,
    outlier_ratio: float = 0.3,
    with_depth: bool = False,
    depth_noise: float = 0.01,
    coincident_centers: bool = False,
    num_points: int = 30_000,
) -> SyntheticCorrespondences:
    """Exact-ground-truth correspondences between a query and ``num_references`` references
    placed within ~1.5 m of it, looking the same way (±10°).

    Args:
        noise_px: std of the Gaussian pixel noise (query keypoints and reference keypoints).
        outlier_ratio: fraction of each reference's matches that are wrong.
        with_depth: fill ``query_depth`` / ``reference_depth`` (metric z-depth, relative
            Gaussian noise ``depth_noise``; outliers get depth of whatever the wrong pixel is,
            modelled as uniform in [2, 12] m).
        coincident_centers: every reference at the same centre (a degenerate configuration).
    """
    rng = np.random.default_rng(seed)
    camera = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
    q_center = rng.uniform([-1.5, -0.5, -2.0], [1.5, 0.5, 0.0])
    R_q = _rotation(rng, np.eye(3), 8.0)
    query_pose = Rigid3d(R_q, -R_q @ q_center)
    points = sample_room_points(rng, num_points)
    q_xy, q_z, q_vis = project_points(camera, query_pose, points)
    points, q_xy, q_z = points[q_vis], q_xy[q_vis], q_z[q_vis]
    q_xy_noisy = q_xy + rng.normal(0.0, noise_px, q_xy.shape)  # one keypoint per point
    shared_center = q_center + rng.uniform([-1.5, -0.5, -1.5], [1.5, 0.5, 1.5])
    references, masks = [], []
    for i in range(num_references):
        center = (
            shared_center
            if coincident_centers
            else q_center + rng.uniform([-1.5, -0.5, -1.5], [1.5, 0.5, 1.5])
        )
        R = _rotation(rng, R_q, 10.0)
        pose = Rigid3d(R, -R @ center)
        r_xy, r_z, r_vis = project_points(camera, pose, points)
        visible = np.flatnonzero(r_vis)
        m = min(matches_per_reference, visible.size)
        chosen = rng.choice(visible, size=m, replace=False)
        num_out = round(outlier_ratio * m)
        is_out = np.zeros(m, dtype=bool)
        is_out[rng.choice(m, size=num_out, replace=False)] = True
        ref_xy = r_xy[chosen] + rng.normal(0.0, noise_px, (m, 2))
        ref_xy[is_out] = rng.uniform([0, 0], [camera.width, camera.height], (num_out, 2))
        query_idx = chosen.copy()
        # wrong matches pair a real query keypoint with the wrong reference pixel
        query_idx[is_out] = rng.choice(points.shape[0], size=num_out)
        query_depth = ref_depth = None
        if with_depth:
            query_depth = q_z[query_idx] * (1.0 + rng.normal(0.0, depth_noise, m))
            ref_depth = r_z[chosen] * (1.0 + rng.normal(0.0, depth_noise, m))
            ref_depth[is_out] = rng.uniform(2.0, 12.0, num_out)
        references.append(
            ReferenceObservation(
                image_id=f"ref{i:02d}",
                camera=camera,
                cam_from_world=pose,
                query_xy=q_xy_noisy[query_idx],
                reference_xy=ref_xy,
                retrieval_score=float(1.0 - 0.03 * i),
                reference_depth=ref_depth,
                query_depth=query_depth,
            )
        )
        masks.append(~is_out)
    return SyntheticCorrespondences(camera, query_pose, references, float(np.median(q_z)), masks)
