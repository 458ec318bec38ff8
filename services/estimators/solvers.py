"""Minimal solvers of our own, batched over B samples: each turns B minimal samples into B
models. PoseLib's 5-point and P3P solvers run inside PoseLib's own loop (``poselib_bridge``).

With a depth d at a normalised point x̃ = (x, y, 1), the 3D point in the camera frame is d·x̃
(z-depth). Three such points seen in two frames fix the similarity between the frames
(Umeyama / Horn); an unknown per-image depth scale only changes its scale and the length of
its translation, so the rotation and the direction of the translation are exact even when
depths are known only up to scale.
"""

from __future__ import annotations

import numpy as np

from services.geometry.depth_pose import back_project, similarity_from_points
from services.types import BoolArray, FloatArray


def relative_pose_3pt_depth(
    x_src: FloatArray, d_src: FloatArray, x_dst: FloatArray, d_dst: FloatArray, with_scale: bool
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Relative pose from three correspondences with depth in both images.

    Args:
        x_src, x_dst: (B, 3, 2) normalised points in the source / destination image.
        d_src, d_dst: (B, 3) depths (> 0) at those points.
        with_scale: depths are known only up to one scale per image (True) or both metric.
    Returns:
        ``dst_from_src`` as R (B, 3, 3) and t (B, 3) (metric when ``with_scale`` is False,
        otherwise in the source depth units), and the scale s (B,).
    """
    return similarity_from_points(
        back_project(x_src, d_src), back_project(x_dst, d_dst), with_scale
    )


def absolute_pose_3pt_depth(
    points_world: FloatArray, points_query: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Query pose from three points known in the world and, by metric depth, in the query
    camera frame: rigid alignment (Umeyama, s = 1).

    Args:
        points_world, points_query: (B, 3, 3) the same three points in both frames.
    Returns:
        Query rotations ``cam_from_world`` (B, 3, 3) and centres (B, 3).
    """
    R, t, _ = similarity_from_points(points_world, points_query, with_scale=False)
    return R, -np.einsum("bji,bj->bi", R, t)


def absolute_pose_3pt_depth_plus_one(
    points_ref: FloatArray,
    points_query: FloatArray,
    R_ref: FloatArray,
    C_ref: FloatArray,
    query_norm_other: FloatArray,
    ray_world_other: FloatArray,
    C_other: FloatArray,
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Query pose from three depth correspondences with a reference A (depths up to one scale
    per image) and one correspondence with another reference B (the "+1", as in E5+1).

    The three points give the similarity query ← A: the query rotation and the direction of the
    query centre from A's centre; B's correspondence fixes the distance along that direction by
    intersecting its query ray with B's ray.

    Args:
        points_ref, points_query: (B, 3, 3) the three points in A's and the query's camera frame.
        R_ref, C_ref: (B, 3, 3) A's ``cam_from_world`` rotations, (B, 3) its centres.
        query_norm_other: (B, 2) normalised query point of B's correspondence.
        ray_world_other: (B, 3) B's ray of that correspondence in world axes.
        C_other: (B, 3) B's centres.
    Returns:
        Query rotations (B, 3, 3), centres (B, 3), and whether each sample gave a pose in front
        of A (B,).
    """
    R_qa, t_qa, _ = similarity_from_points(points_ref, points_query, with_scale=True)
    R_q = R_qa @ R_ref
    v = np.einsum("bji,bj->bi", R_q, t_qa)  # C_q = C_A − λ·R_qᵀ t_qa, λ > 0 (unit depth scale)
    ones = np.ones(query_norm_other.shape[0])
    a = np.einsum("bji,bj->bi", R_q, np.c_[query_norm_other, ones])
    n = np.cross(a, ray_world_other)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = ((C_ref - C_other) * n).sum(axis=1) / (v * n).sum(axis=1)
    return R_q, C_ref - lam[:, None] * v, np.isfinite(lam) & (lam > 0)
