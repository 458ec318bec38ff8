"""Guarded PoseLib calls and pose conversions.

PoseLib 2.0.5 ``estimate_generalized_relative_pose`` loops forever when fewer than two pairs
have matches or no pair has ≥ 5 (a known pitfall of that version). Every call here checks its input
sizes first, passes empty arrays as ``np.zeros((0, 2))``, and bounds its iterations. Pixel
thresholds are in pixels (PoseLib scales them by the focal lengths internally).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import poselib

from services.estimators.base import ReferenceObservation
from services.estimators.options import RansacOptions
from services.estimators.ransac import Deadline
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.types import BoolArray, FloatArray

# Rough PoseLib LO-RANSAC throughput on one core, in (iterations × correspondences) per second
# (measured ≈ 1–3e7 here for the relative and generalized relative pose estimators; 100
# refinement steps on 70k matches took 0.5 s), used to turn a time budget into an iteration
# cap, and into the first slice of a refinement short of time.
_MATCH_EVALUATIONS_PER_SECOND = 1.0e7
# a refinement short of time runs in slices of about this long (the first at the model's
# throughput, the others at the one measured), checking the time left between them
_FIRST_SLICE_S = 0.05
_SLICE_S = 0.1


def to_poselib(pose: Rigid3d) -> poselib.CameraPose:
    out = poselib.CameraPose()
    out.q = pose.quaternion
    out.t = pose.translation
    return out


def from_poselib(pose: poselib.CameraPose) -> Rigid3d:
    return Rigid3d.from_quaternion(np.asarray(pose.q, dtype=np.float64), np.asarray(pose.t))


def _points(xy: FloatArray) -> FloatArray:
    xy = np.asarray(xy, dtype=np.float64)
    return np.ascontiguousarray(xy.reshape(-1, 2)) if xy.size else np.zeros((0, 2))


def ransac_options(
    options: RansacOptions,
    deadline: Deadline,
    calls_left: int = 1,
    epipolar_px: float | None = None,
    reprojection_px: float | None = None,
    num_matches: int = 1000,
) -> dict[str, Any]:
    """PoseLib RANSAC options from ours, with the threshold of the problem's error, pixels;
    with a time budget the iteration cap shrinks to what the remaining budget, shared by
    ``calls_left`` calls, allows for ``num_matches`` correspondences (a rough throughput
    model; the bound is soft)."""
    max_iterations = options.max_iterations
    remaining = deadline.remaining_s()
    if np.isfinite(remaining):
        share = max(remaining, 0.0) / max(calls_left, 1)
        affordable = share * _MATCH_EVALUATIONS_PER_SECOND / max(num_matches, 1)
        max_iterations = min(max_iterations, max(50, int(affordable)))
    out: dict[str, Any] = {
        "min_iterations": min(options.min_iterations, max_iterations),
        "max_iterations": max_iterations,
        "success_prob": options.success_prob,
        "seed": options.seed,
    }
    if epipolar_px is not None:
        out["max_epipolar_error"] = epipolar_px
    if reprojection_px is not None:
        out["max_reproj_error"] = reprojection_px
    return out


def bundle_options(loss_scale_px: float, max_iterations: int = 100) -> dict[str, Any]:
    return {"loss_type": "CAUCHY", "loss_scale": loss_scale_px, "max_iterations": max_iterations}


def estimate_relative_pose(
    ref: ReferenceObservation, query_camera: Camera, ransac: dict[str, Any], loss_scale_px: float
) -> tuple[Rigid3d, BoolArray, int] | None:
    """5-point LO-RANSAC relative pose ``query_from_reference`` (unit translation), its inlier
    mask and iteration count; None with fewer than 5 matches or a non-finite result."""
    if ref.num_matches < 5:
        return None
    pose, info = poselib.estimate_relative_pose(
        _points(ref.reference_xy),
        _points(ref.query_xy),
        ref.camera.to_poselib(),
        query_camera.to_poselib(),
        ransac,
        bundle_options(loss_scale_px),
    )
    rigid = from_poselib(pose)
    inliers = np.asarray(info.get("inliers", []), dtype=bool)
    if inliers.shape[0] != ref.num_matches or not np.all(np.isfinite(rigid.matrix)):
        return None
    return rigid, inliers, int(info.get("iterations", 0))


def refine_relative_pose(
    ref_xy: FloatArray,
    query_xy: FloatArray,
    initial: Rigid3d,
    ref_camera: Camera,
    query_camera: Camera,
    loss_scale_px: float,
) -> Rigid3d:
    """Sampson-error refinement of ``query_from_reference`` on the given (inlier) matches."""
    if ref_xy.shape[0] < 5:
        return initial
    pose, _ = poselib.refine_relative_pose(
        _points(ref_xy),
        _points(query_xy),
        to_poselib(initial),
        ref_camera.to_poselib(),
        query_camera.to_poselib(),
        bundle_options(loss_scale_px),
    )
    out = from_poselib(pose)
    return out if np.all(np.isfinite(out.matrix)) else initial


def generalized_refinement_possible(counts: list[int]) -> bool:
    """The generalized relative pose entry points need ≥ 2 non-empty pairs, one with ≥ 5."""
    nonempty = [c for c in counts if c > 0]
    return len(nonempty) >= 2 and max(nonempty) >= 5


def refine_query_pose(
    references: list[ReferenceObservation],
    masks: list[BoolArray],
    query_camera: Camera,
    initial: Rigid3d,
    loss_scale_px: float,
    max_iterations: int = 100,
    deadline: Deadline | None = None,
    reserve_s: float = 0.0,
) -> Rigid3d:
    """Refine the query ``cam_from_world`` on the masked matches of all references at once
    (PoseLib generalized relative pose refinement: the references form a rig whose frame is
    the world; Sampson error; at most ``max_iterations`` Levenberg–Marquardt steps). Returns
    ``initial`` when the guard refuses the call.

    With a ``deadline`` the refinement ends ``reserve_s`` before it: when the throughput model
    says the steps need more than half of that time, they run in slices of at most
    ``_SLICE_S`` (each continuing from the last, its throughput measured), and no slice starts
    that would not end in time; otherwise (ample time) in one call, as without a deadline."""
    used = [i for i, m in enumerate(masks) if int(m.sum()) > 0]
    if not generalized_refinement_possible([int(masks[i].sum()) for i in used]):
        return initial
    matches = []
    for pair_index, i in enumerate(used):
        m = poselib.PairwiseMatches()
        m.cam_id1 = pair_index
        m.cam_id2 = 0
        m.x1 = _points(references[i].reference_xy[masks[i]])
        m.x2 = _points(references[i].query_xy[masks[i]])
        matches.append(m)
    rig = [to_poselib(references[i].cam_from_world) for i in used]
    cameras = [references[i].camera.to_poselib() for i in used]

    def refine(pose: Rigid3d, iterations: int) -> tuple[Rigid3d, int]:
        refined, info = poselib.refine_generalized_relative_pose(
            matches,
            to_poselib(pose),
            rig,
            cameras,
            [to_poselib(Rigid3d.identity())],
            [query_camera.to_poselib()],
            bundle_options(loss_scale_px, iterations),
        )
        out = from_poselib(refined)
        if not np.all(np.isfinite(out.matrix)):
            return pose, 0
        return out, int(info.get("iterations", iterations))

    residuals = max(sum(int(masks[i].sum()) for i in used), 1)
    left = float("inf") if deadline is None else deadline.remaining_s() - reserve_s
    rate = _MATCH_EVALUATIONS_PER_SECOND
    if max_iterations * residuals / rate <= 0.5 * left:
        return refine(initial, max_iterations)[0]
    pose, done, slice_s = initial, 0, _FIRST_SLICE_S
    while done < max_iterations and deadline is not None:
        left = deadline.remaining_s() - reserve_s
        steps = min(max_iterations - done, int(min(left, slice_s) * rate / residuals))
        if steps < 1:
            break
        start = time.perf_counter()
        pose, ran = refine(pose, steps)
        rate = max(ran, 1) * residuals / max(time.perf_counter() - start, 1e-6)
        done, slice_s = done + steps, _SLICE_S
        if ran < steps:  # converged (or not finite)
            break
    return pose


def estimate_absolute_pose(
    points2d: FloatArray,
    points3d: FloatArray,
    camera: Camera,
    ransac: dict[str, Any],
    loss_scale_px: float,
) -> tuple[Rigid3d, BoolArray, int] | None:
    """P3P LO-RANSAC + refinement; None with fewer than 4 correspondences."""
    if points2d.shape[0] < 4:
        return None
    pose, info = poselib.estimate_absolute_pose(
        _points(points2d),
        np.ascontiguousarray(points3d, dtype=np.float64).reshape(-1, 3),
        camera.to_poselib(),
        ransac,
        bundle_options(loss_scale_px),
    )
    rigid = from_poselib(pose)
    inliers = np.asarray(info.get("inliers", []), dtype=bool)
    if inliers.shape[0] != points2d.shape[0] or not np.all(np.isfinite(rigid.matrix)):
        return None
    return rigid, inliers, int(info.get("iterations", 0))


def refine_absolute_pose(
    points2d: FloatArray,
    points3d: FloatArray,
    camera: Camera,
    initial: Rigid3d,
    loss_scale_px: float,
) -> Rigid3d:
    if points2d.shape[0] < 4:
        return initial
    pose, _ = poselib.refine_absolute_pose(
        _points(points2d),
        np.ascontiguousarray(points3d, dtype=np.float64).reshape(-1, 3),
        to_poselib(initial),
        camera.to_poselib(),
        bundle_options(loss_scale_px),
    )
    out = from_poselib(pose)
    return out if np.all(np.isfinite(out.matrix)) else initial


def estimate_generalized_absolute_pose(
    points2d: list[FloatArray],
    points3d: list[FloatArray],
    cam_from_rig: list[Rigid3d],
    cameras: list[Camera],
    ransac: dict[str, Any],
    loss_scale_px: float,
) -> tuple[Rigid3d, list[BoolArray], int] | None:
    """``rig_from_world`` of a rig of cameras (``cam_from_rig`` each) from the 2D–3D matches of
    each camera: minimal generalized P3P (GP3P) in LO-RANSAC with non-linear refinement
    (PoseLib). Returns the pose, one inlier mask per camera and the iteration count; None with
    fewer than 4 correspondences in all or a non-finite result."""
    if sum(int(p.shape[0]) for p in points2d) < 4:
        return None
    pose, info = poselib.estimate_generalized_absolute_pose(
        [_points(p) for p in points2d],
        [np.ascontiguousarray(p, dtype=np.float64).reshape(-1, 3) for p in points3d],
        [to_poselib(p) for p in cam_from_rig],
        [camera.to_poselib() for camera in cameras],
        ransac,
        bundle_options(loss_scale_px),
    )
    rigid = from_poselib(pose)
    inliers = [np.asarray(mask, dtype=bool).reshape(-1) for mask in info.get("inliers", [])]
    if len(inliers) != len(points2d) or not np.all(np.isfinite(rigid.matrix)):
        return None
    if any(m.shape[0] != p.shape[0] for m, p in zip(inliers, points2d, strict=True)):
        return None
    return rigid, inliers, int(info.get("iterations", 0))
