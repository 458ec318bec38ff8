"""Relative pose of one query–reference pair from the 3-point-with-depth solver in LO-RANSAC.

Hypotheses come in batches from ``solvers.relative_pose_3pt_depth`` (Umeyama on three
back-projected points per image) and run through ``ransac.lo_ransac`` (truncated Sampson
error, preemptive scoring on a subset). Local optimisation re-fits the similarity on all
inliers that have depth. ``polish_relative_pose`` then runs PoseLib's Sampson refinement on
adaptive inlier sets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.estimators.options import RansacOptions
from services.estimators.poselib_bridge import refine_relative_pose
from services.estimators.ransac import Deadline, lo_ransac, msac_score
from services.estimators.robust_scale import adaptive_threshold_px
from services.estimators.solvers import relative_pose_3pt_depth
from services.geometry.camera import Camera
from services.geometry.depth_pose import back_project, sampson_errors, similarity_from_points
from services.geometry.rigid import Rigid3d
from services.types import BoolArray, FloatArray, IntArray

# a relative pose ``dst_from_src``: rotation (3, 3) and translation (3,)
Pose = tuple[FloatArray, FloatArray]
# B relative poses: rotations (B, 3, 3) and translations (B, 3)
Poses = tuple[FloatArray, FloatArray]


@dataclass(frozen=True)
class DepthRelativePose:
    """``dst_from_src`` rotation, unit translation direction, and RANSAC iterations run."""

    R: FloatArray
    t: FloatArray
    iterations: int


class _DepthPairProblem:
    """LO-RANSAC problem of one pair: M normalised correspondences with depths (0 = none)."""

    sample_size = 3
    batch_size = 200
    scoring_subset = 256

    def __init__(
        self,
        x_src: FloatArray,
        d_src: FloatArray,
        x_dst: FloatArray,
        d_dst: FloatArray,
        threshold: float,
        with_scale: bool,
    ) -> None:
        self.x_src, self.d_src, self.x_dst, self.d_dst = x_src, d_src, x_dst, d_dst
        self.P_src, self.P_dst = back_project(x_src, d_src), back_project(x_dst, d_dst)
        self.has_depth = (d_src > 0) & (d_dst > 0)
        self.with_depth = np.flatnonzero(self.has_depth)
        self.threshold = threshold
        self.with_scale = with_scale
        self.num_data = int(x_src.shape[0])

    def hypotheses(self, rng: np.random.Generator) -> Poses | None:
        sample = self.with_depth[rng.integers(0, self.with_depth.size, size=(self.batch_size, 3))]
        distinct = (
            (sample[:, 0] != sample[:, 1])
            & (sample[:, 0] != sample[:, 2])
            & (sample[:, 1] != sample[:, 2])
        )
        sample = sample[distinct]
        tri = self.P_src[sample]
        area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        sample = sample[area > 1e-9]
        if sample.shape[0] == 0:
            return None
        R, t, _ = relative_pose_3pt_depth(
            self.x_src[sample],
            self.d_src[sample],
            self.x_dst[sample],
            self.d_dst[sample],
            self.with_scale,
        )
        return R, t

    def batch_errors(self, batch: Poses, subset: IntArray) -> FloatArray:
        return sampson_errors(batch[0], batch[1], self.x_src[subset], self.x_dst[subset])

    def select(self, batch: Poses, k: int) -> Pose:
        return batch[0][k], batch[1][k]

    def errors(self, model: Pose) -> FloatArray:
        errors: FloatArray = sampson_errors(model[0][None], model[1][None], self.x_src, self.x_dst)[
            0
        ]
        return errors

    def local_optimisation(self, model: Pose, errors: FloatArray) -> tuple[Pose, FloatArray]:
        """Re-fit the similarity on all inliers with depth while the MSAC score improves."""
        score = float(msac_score(errors, self.threshold))
        for _ in range(3):
            inl = (errors < self.threshold) & self.has_depth
            if inl.sum() < 3:
                break
            R, t, _ = similarity_from_points(
                self.P_src[inl][None], self.P_dst[inl][None], self.with_scale
            )
            new_errors = sampson_errors(R, t, self.x_src, self.x_dst)[0]
            new = float(msac_score(new_errors, self.threshold))
            if new >= score:
                break
            score, model, errors = new, (R[0], t[0]), new_errors
        return model, errors


def ransac_relative_pose_depth(
    x_src: FloatArray,
    d_src: FloatArray,
    x_dst: FloatArray,
    d_dst: FloatArray,
    threshold: float,
    options: RansacOptions,
    rng: np.random.Generator,
    deadline: Deadline,
    with_scale: bool = True,
) -> DepthRelativePose | None:
    """LO-RANSAC over the 3-point-with-depth solver.

    Args:
        x_src, x_dst: (M, 2) normalised correspondences; d_src, d_dst: (M,) depths (0 = none).
        threshold: Sampson inlier threshold in normalised units (pixels / focal).
        options: iteration bounds and success probability (its threshold and seed are not
            used: ``threshold`` and ``rng`` are).
        with_scale: depths known up to one scale per image (similarity) or metric (rigid).
    Returns:
        The best model, or None when fewer than 3 matches have both depths.
    """
    problem = _DepthPairProblem(x_src, d_src, x_dst, d_dst, threshold, with_scale)
    if problem.with_depth.size < 3 or problem.num_data < 5:
        return None
    found = lo_ransac(problem, threshold, options, rng, deadline)
    if found.model is None:
        return None
    R_best, t_best = found.model
    norm = float(np.linalg.norm(t_best))
    direction = t_best / norm if norm > 0 else t_best
    return DepthRelativePose(R_best, direction, found.iterations)


def polish_relative_pose(
    model: DepthRelativePose,
    ref_xy: FloatArray,
    query_xy: FloatArray,
    x_ref: FloatArray,
    x_query: FloatArray,
    ref_camera: Camera,
    query_camera: Camera,
    threshold: float,
    focal: float,
    rounds: int = 3,
) -> tuple[Rigid3d, BoolArray]:
    """PoseLib Sampson refinement of a ``query_from_ref`` model, ``rounds`` times, each on the
    matches within an adaptive threshold (≤ ``threshold``, normalised units). Returns the pose
    (unit translation) and its inliers at ``threshold``."""
    pose = Rigid3d(model.R, model.t)
    errors = sampson_errors(model.R[None], model.t[None], x_ref, x_query)[0] * focal
    for _ in range(rounds):
        thr_px = adaptive_threshold_px(errors, threshold * focal)
        keep = errors < thr_px
        refined = refine_relative_pose(
            ref_xy[keep], query_xy[keep], pose, ref_camera, query_camera, thr_px / 4.0
        )
        new_errors = (
            sampson_errors(refined.rotation[None], refined.translation[None], x_ref, x_query)[0]
            * focal
        )
        if (new_errors < threshold * focal).sum() < 0.95 * (errors < threshold * focal).sum():
            break
        pose, errors = refined, new_errors
    return pose, errors < threshold * focal
