"""Pose triangulation ("Ess. mat." in Panek et al. 2025, "A Guide to Structureless Visual
Localization"), shared by ``essential_5pt``, ``essential_3pt_depth``
(``PoseTriangulationEstimator``) and the first stages of ``motion_averaging``
(``triangulated_pose``).

1. Relative pose ``query_from_reference`` per pair (rotation + unit translation direction).
2. Each pair implies a query rotation ``R_q = R_qr·R_r``: robust single-rotation averaging.
3. Each pair implies a ray from the reference centre on which the query centre lies:
   ``C_q = C_r − λ·R_qᵀ·t_qr`` (λ > 0). The rays are intersected robustly (RANSAC over pairs,
   or IRLS for LazyLoc), then by least squares over the inlier rays.
4. Local optimisation: PoseLib generalized relative pose refinement (Sampson error) of the
   query pose on the inlier matches of all pairs at once, twice, re-selecting the inliers.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from services.estimators.base import FailureReason, ReferenceObservation
from services.estimators.correspondences import (
    StackedMatches,
    pose_sampson_errors_px,
    random_subset,
)
from services.estimators.depth_relative_pose import (
    polish_relative_pose,
    ransac_relative_pose_depth,
)
from services.estimators.estimator import Estimator, Request, Solution
from services.estimators.options import EstimatorOptions
from services.estimators.poselib_bridge import (
    estimate_relative_pose,
    ransac_options,
    refine_query_pose,
)
from services.estimators.ransac import Deadline
from services.estimators.robust_scale import adaptive_threshold_px
from services.geometry.averaging import (
    average_rotations,
    irls_ray_intersection,
    ransac_ray_intersection,
)
from services.geometry.camera import Camera
from services.geometry.depth_pose import sampson_errors
from services.geometry.projection import mean_focal, normalized_from_pixels
from services.geometry.rigid import Rigid3d
from services.types import BoolArray, FloatArray

ROTATION_INLIER_DEG = 5.0  # implied query rotations farther than this from the median
DIRECTION_INLIER_DEG = 10.0  # rays farther than this from the query centre
MIN_PAIR_INLIERS = 15  # a relative pose with fewer inliers is not used
MIN_CONDITIONING = 1e-6  # ray-intersection conditioning below this is degenerate
# Sampson errors a pass evaluates per second before one was timed (measured ~2e6 unloaded)
_PASS_MATCHES_PER_SECOND = 1.0e6


@dataclass(frozen=True)
class PairPose:
    """A query–reference relative pose: ``query_from_ref`` with unit translation."""

    index: int
    query_from_ref: Rigid3d
    inliers: BoolArray
    iterations: int


RelativePoseSolver = Callable[
    [ReferenceObservation, Camera, EstimatorOptions, Deadline, int, np.random.Generator],
    PairPose | None,
]


def solve_5pt(
    ref: ReferenceObservation,
    query_camera: Camera,
    options: EstimatorOptions,
    deadline: Deadline,
    calls_left: int,
    rng: np.random.Generator,
) -> PairPose | None:
    """PoseLib 5-point LO-RANSAC with Sampson refinement (``index`` filled by the caller)."""
    ransac = ransac_options(
        options.ransac,
        deadline,
        calls_left,
        epipolar_px=options.ransac.max_error_px,
        num_matches=ref.num_matches,
    )
    out = estimate_relative_pose(ref, query_camera, ransac, options.ransac.max_error_px / 4.0)
    if out is None:
        return None
    return PairPose(-1, out[0], out[1], out[2])


def solve_3pt_depth(
    ref: ReferenceObservation,
    query_camera: Camera,
    options: EstimatorOptions,
    deadline: Deadline,
    calls_left: int,
    rng: np.random.Generator,
) -> PairPose | None:
    """Our 3-point-with-depth LO-RANSAC (similarity: depth scale per image unknown), then
    PoseLib Sampson refinement on adaptive inlier sets."""
    if ref.query_depth is None or ref.reference_depth is None or ref.num_matches < 5:
        return None
    x_ref = normalized_from_pixels(ref.camera, ref.reference_xy)
    x_q = normalized_from_pixels(query_camera, ref.query_xy)
    focal = 0.5 * (mean_focal(ref.camera) + mean_focal(query_camera))
    d_ref = np.where(np.isfinite(ref.reference_depth), ref.reference_depth, 0.0)
    d_q = np.where(np.isfinite(ref.query_depth), ref.query_depth, 0.0)
    model = ransac_relative_pose_depth(
        x_ref,
        d_ref,
        x_q,
        d_q,
        options.ransac.max_error_px / focal,
        options.ransac,
        rng,
        deadline,
        with_scale=True,
    )
    if model is None:
        return None
    refined, inliers = polish_relative_pose(
        model,
        ref.reference_xy,
        ref.query_xy,
        x_ref,
        x_q,
        ref.camera,
        query_camera,
        options.ransac.max_error_px / focal,
        focal,
    )
    return PairPose(-1, refined, inliers, model.iterations)


def sampled_solver(solver: RelativePoseSolver, cap: int) -> RelativePoseSolver:
    """``solver`` run on a seeded random sample of at most ``cap`` of a pair's matches (its
    hypotheses are scored on fewer matches: RANSAC's cost is iterations × matches); the
    returned inlier mask covers all the pair's matches (Sampson error within
    ``max_error_px``). The pose itself is as precise as the sample allows: a proposal for
    robust averaging, not a final answer."""

    def solve(
        ref: ReferenceObservation,
        query_camera: Camera,
        options: EstimatorOptions,
        deadline: Deadline,
        calls_left: int,
        rng: np.random.Generator,
    ) -> PairPose | None:
        if ref.num_matches <= cap:
            return solver(ref, query_camera, options, deadline, calls_left, rng)
        s = random_subset(ref.num_matches, cap, rng)
        sample = replace(
            ref,
            query_xy=ref.query_xy[s],
            reference_xy=ref.reference_xy[s],
            query_depth=None if ref.query_depth is None else ref.query_depth[s],
            reference_depth=None if ref.reference_depth is None else ref.reference_depth[s],
        )
        pair = solver(sample, query_camera, options, deadline, calls_left, rng)
        if pair is None:
            return None
        pose = pair.query_from_ref
        errors = sampson_errors(
            pose.rotation[None],
            pose.translation[None],
            normalized_from_pixels(ref.camera, ref.reference_xy),
            normalized_from_pixels(query_camera, ref.query_xy),
        )[0]
        focal = 0.5 * (mean_focal(ref.camera) + mean_focal(query_camera))
        return PairPose(
            pair.index, pose, errors * focal < options.ransac.max_error_px, pair.iterations
        )

    return solve


def pairwise_poses(
    query_camera: Camera,
    references: list[ReferenceObservation],
    options: EstimatorOptions,
    deadline: Deadline,
    solver: RelativePoseSolver,
) -> tuple[list[PairPose], bool]:
    """Relative pose of every pair with enough matches; also whether the budget ran out."""
    rng = np.random.default_rng(options.ransac.seed)
    order = [i for i, ref in enumerate(references) if ref.num_matches >= 5]
    out: list[PairPose] = []
    for k, i in enumerate(order):
        if deadline.expired():
            return out, True
        pair = solver(references[i], query_camera, options, deadline, len(order) - k, rng)
        if pair is not None and int(pair.inliers.sum()) >= MIN_PAIR_INLIERS:
            out.append(PairPose(i, pair.query_from_ref, pair.inliers, pair.iterations))
    return out, False


@dataclass(frozen=True)
class TriangulatedPose:
    pose: Rigid3d | None
    failure: FailureReason | None
    pair_inliers: BoolArray  # over the pairs: consistent in rotation and direction
    conditioning: float


def triangulate_pose(
    pairs: list[PairPose],
    references: list[ReferenceObservation],
    robust: str = "ransac",
) -> TriangulatedPose:
    """Steps 2–3: rotation averaging and camera-centre triangulation.

    Args:
        robust: ``"ransac"`` (RANSAC over ray pairs) or ``"irls"`` (Cauchy-weighted least
            squares, LazyLoc style).
    """
    n = len(pairs)
    if n < 2:
        return TriangulatedPose(None, FailureReason.TOO_FEW_MATCHES, np.zeros(n, bool), 0.0)
    R_rel = np.stack([p.query_from_ref.rotation for p in pairs])
    t_rel = np.stack([p.query_from_ref.translation for p in pairs])
    t_rel /= np.maximum(np.linalg.norm(t_rel, axis=1, keepdims=True), 1e-12)
    R_refs = np.stack([references[p.index].cam_from_world.rotation for p in pairs])
    origins = np.stack([references[p.index].cam_from_world.center for p in pairs])
    weights = np.array([float(p.inliers.sum()) for p in pairs])
    R_q, rot_inl = average_rotations(R_rel @ R_refs, weights, ROTATION_INLIER_DEG)
    directions = -(t_rel @ R_q)  # −R_qᵀ t for each pair
    if rot_inl.sum() < 2:
        return TriangulatedPose(None, FailureReason.NO_CONSENSUS, rot_inl, 0.0)
    idx = np.flatnonzero(rot_inl)
    if robust == "irls":
        C, ray_inl, cond = irls_ray_intersection(
            origins[idx], directions[idx], weights[idx], DIRECTION_INLIER_DEG
        )
    else:
        C, ray_inl, cond = ransac_ray_intersection(
            origins[idx], directions[idx], weights[idx], DIRECTION_INLIER_DEG, MIN_CONDITIONING
        )
    inliers = np.zeros(n, dtype=bool)
    inliers[idx[ray_inl]] = True
    if not np.all(np.isfinite(C)) or cond < MIN_CONDITIONING:
        return TriangulatedPose(None, FailureReason.DEGENERATE_GEOMETRY, inliers, cond)
    if inliers.sum() < 2:
        return TriangulatedPose(None, FailureReason.NO_CONSENSUS, inliers, cond)
    return TriangulatedPose(Rigid3d(R_q, -R_q @ C), None, inliers, cond)


def local_optimisation(
    pose: Rigid3d,
    stacked: StackedMatches,
    references: list[ReferenceObservation],
    query_camera: Camera,
    options: EstimatorOptions,
    deadline: Deadline,
    rounds: int = 3,
    refine_iterations: int = 100,
    errors: FloatArray | None = None,
) -> tuple[Rigid3d, FloatArray]:
    """Step 4: generalized Sampson refinement (PoseLib, Cauchy loss) of the query pose on all
    pairs at once, ``rounds`` times; each round re-selects the matches within an adaptive
    threshold (``adaptive_threshold_px``), with at most ``refine_iterations`` Levenberg–Marquardt
    steps. A round that loses more than 5 % of the inliers at ``max_error_px`` is rejected.

    The time budget: every pass over the stacked matches polls ``deadline``; a round is
    skipped once less time is left than twice the last pass took (its refinement and the
    pass after it would not end in time), and the refinement ends in time for that pass
    (``refine_query_pose``).

    Args:
        errors: (N,) the Sampson errors of ``pose`` (px) when the caller has them.
    Returns:
        The pose and its (N,) Sampson errors (px) over the stacked matches.

    Raises:
        DeadlinePassedError: the deadline passed during a pass.
    """
    thr = options.ransac.max_error_px
    pass_s = stacked.size / _PASS_MATCHES_PER_SECOND
    if errors is None:
        start = time.perf_counter()
        errors = pose_sampson_errors_px(
            stacked, pose.rotation[None], pose.center[None], deadline=deadline
        )[0]
        pass_s = time.perf_counter() - start
    count = int((errors < thr).sum())
    for _ in range(rounds):
        if deadline.remaining_s() < 2.0 * pass_s:
            break
        refine_thr = adaptive_threshold_px(errors, thr)
        selected = errors < refine_thr
        refined = refine_query_pose(
            references,
            stacked.split(selected),
            query_camera,
            pose,
            refine_thr / 4.0,
            refine_iterations,
            deadline,
            reserve_s=pass_s,
        )
        start = time.perf_counter()
        new_errors = pose_sampson_errors_px(
            stacked, refined.rotation[None], refined.center[None], deadline=deadline
        )[0]
        pass_s = time.perf_counter() - start
        new_count = int((new_errors < thr).sum())
        if new_count < 0.95 * count:
            break
        pose, errors, count = refined, new_errors, new_count
    return pose, errors


def triangulated_pose(
    request: Request,
    solver: RelativePoseSolver,
    robust: str = "ransac",
    pair_options: EstimatorOptions | None = None,
) -> Rigid3d:
    """Steps 1–3 with the given relative-pose solver (run with ``pair_options``, by default the
    request's); fails the request without a pose."""
    pairs, timed_out = pairwise_poses(
        request.query_camera,
        request.references,
        pair_options or request.options,
        request.deadline,
        solver,
    )
    request.stats["iterations"] = float(sum(p.iterations for p in pairs))
    request.stats["pairs_with_relative_pose"] = float(len(pairs))
    if timed_out:
        request.fail(FailureReason.TIME_BUDGET_EXCEEDED)
    if len(pairs) < 2:
        request.fail(FailureReason.NO_CONSENSUS)
    tri = triangulate_pose(pairs, request.references, robust)
    request.stats["pairs_consistent"] = float(tri.pair_inliers.sum())
    request.stats["ray_conditioning"] = tri.conditioning
    if tri.pose is None:
        request.fail(tri.failure or FailureReason.NO_CONSENSUS)
    return tri.pose


class PoseTriangulationEstimator(Estimator):
    """Steps 1–4 with the estimator's relative-pose solver; the result's inliers are the
    matches within ``max_error_px`` Sampson error of the final pose."""

    def __init__(self, solver: RelativePoseSolver) -> None:
        self.solver = solver

    def solve(self, request: Request) -> Solution:
        pose, errors = local_optimisation(
            triangulated_pose(request, self.solver),
            request.stacked,
            request.references,
            request.query_camera,
            request.options,
            request.deadline,
        )
        return Solution(pose, errors < request.options.ransac.max_error_px)
