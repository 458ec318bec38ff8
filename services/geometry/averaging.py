"""Single-rotation averaging and camera-centre triangulation from translation directions.

Both are the "pose triangulation" step of structureless localisation: every query–reference
relative pose implies one estimate of the query rotation and one ray from the reference centre
on which the query centre lies.
"""

from __future__ import annotations

import numpy as np

from services.types import BoolArray, FloatArray, IntArray


def project_to_rotation(M: FloatArray) -> FloatArray:
    """Nearest rotation (Frobenius) to each (..., 3, 3) matrix; NaN for a non-finite one
    (the SVD would not converge)."""
    finite: BoolArray = np.asarray(np.isfinite(M).all(axis=(-2, -1)))
    U, _, Vt = np.linalg.svd(np.where(finite[..., None, None], M, np.eye(3)))
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones(M.shape[:-1])
    D[..., 2] = d
    R = (U * D[..., None, :]) @ Vt
    return np.asarray(np.where(finite[..., None, None], R, np.nan), dtype=np.float64)


def rotation_log(R: FloatArray) -> FloatArray:
    """Axis-angle vectors (..., 3) of rotations (..., 3, 3)."""
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos)
    w = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        axis=-1,
    )
    sin = np.sin(angle)
    scale = np.where(sin > 1e-9, angle / (2.0 * np.maximum(sin, 1e-12)), 0.5)
    out = w * scale[..., None]
    # near π the antisymmetric part vanishes: take the axis from R + I instead
    near_pi = angle > np.pi - 1e-4
    if np.any(near_pi):
        B = (R[near_pi] + np.eye(3)) / 2.0
        cols = np.argmax(np.linalg.norm(B, axis=-2), axis=-1)
        axes = B[np.arange(B.shape[0]), :, cols]
        axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
        out[near_pi] = axes * angle[near_pi][:, None]
    return np.asarray(out, dtype=np.float64)


def rotation_exp(w: FloatArray) -> FloatArray:
    """Rotations (..., 3, 3) of axis-angle vectors (..., 3) (Rodrigues)."""
    angle = np.linalg.norm(w, axis=-1)
    axis = w / np.maximum(angle, 1e-12)[..., None]
    K = np.zeros((*w.shape[:-1], 3, 3))
    K[..., 0, 1], K[..., 0, 2] = -axis[..., 2], axis[..., 1]
    K[..., 1, 0], K[..., 1, 2] = axis[..., 2], -axis[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -axis[..., 1], axis[..., 0]
    s, c = np.sin(angle)[..., None, None], np.cos(angle)[..., None, None]
    return np.asarray(np.eye(3) + s * K + (1.0 - c) * (K @ K), dtype=np.float64)


def angles_between_deg(R: FloatArray, Rs: FloatArray) -> FloatArray:
    """(N,) angles in degrees between R (3, 3) and each of Rs (N, 3, 3)."""
    cos = (np.einsum("ij,nij->n", R, Rs) - 1.0) / 2.0
    return np.asarray(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), dtype=np.float64)


def average_rotations(
    rotations: FloatArray, weights: FloatArray, inlier_deg: float, iterations: int = 20
) -> tuple[FloatArray, BoolArray]:
    """Robust single-rotation averaging: geodesic L1 median (Weiszfeld in the tangent space,
    started at the weighted medoid), then a chordal L2 mean over the estimates within
    ``inlier_deg`` of the median.

    Args:
        rotations: (N, 3, 3) estimates of one rotation; weights: (N,) non-negative.
        inlier_deg: estimates farther than this from the median are outliers.
    Returns:
        (3, 3) rotation and (N,) inlier mask.
    """
    weights = np.asarray(weights, dtype=np.float64)
    pairwise = np.stack([angles_between_deg(R, rotations) for R in rotations])  # N ≤ top-k
    R = rotations[int(np.argmin(pairwise @ weights))]
    for _ in range(iterations):
        v = rotation_log(np.einsum("ji,njk->nik", R, rotations))  # tangent at R: log(Rᵀ R_i)
        dist = np.linalg.norm(v, axis=1)
        w = weights / np.maximum(dist, 1e-9)
        step = (w[:, None] * v).sum(axis=0) / max(float(w.sum()), 1e-12)
        R = R @ rotation_exp(step)
        if np.linalg.norm(step) < 1e-10:
            break
    inliers = angles_between_deg(R, rotations) <= inlier_deg
    if inliers.any():
        M = np.einsum("n,nij->ij", weights[inliers], rotations[inliers])
        R = project_to_rotation(M)
    return np.asarray(R, dtype=np.float64), inliers


def intersect_rays(
    origins: FloatArray, directions: FloatArray, weights: FloatArray
) -> tuple[FloatArray, float]:
    """Least-squares point closest to weighted lines ``origin + s·direction``.

    Args:
        origins, directions: (N, 3); weights: (N,).
    Returns:
        (3,) point and the conditioning of the problem: the ratio of the smallest to the largest
        eigenvalue of Σ w (I − d dᵀ) (0 when all lines are parallel or an input is not finite,
        i.e. degenerate; the point is then NaN).
    """
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    A = np.einsum("n,nij->ij", weights, P)
    b = np.einsum("n,nij,nj->i", weights, P, origins)
    if not (np.isfinite(A).all() and np.isfinite(b).all()):
        return np.full(3, np.nan), 0.0
    eig = np.linalg.eigvalsh(A)
    cond = float(eig[0] / max(eig[-1], 1e-300))
    if cond < 1e-12:
        return np.full(3, np.nan), cond
    return np.asarray(np.linalg.solve(A, b), dtype=np.float64), cond


def _intersect_pairs(
    origins: FloatArray, directions: FloatArray, first: IntArray, second: IntArray
) -> tuple[FloatArray, FloatArray]:
    """``intersect_rays`` of each pair of rays (``first[k]``, ``second[k]``) with unit
    weights, batched: (K, 3) points (NaN where degenerate) and (K,) conditionings."""
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    Po = np.einsum("nij,nj->ni", P, origins)
    A = P[first] + P[second]
    b = Po[first] + Po[second]
    finite = np.isfinite(A).all(axis=(1, 2)) & np.isfinite(b).all(axis=1)
    A = np.where(finite[:, None, None], A, np.eye(3))
    eig = np.linalg.eigvalsh(A)
    conds = np.where(finite, eig[:, 0] / np.maximum(eig[:, -1], 1e-300), 0.0)
    solvable = conds >= 1e-12
    points = np.full((len(first), 3), np.nan)
    if solvable.any():
        points[solvable] = np.linalg.solve(A[solvable], b[solvable][:, :, None])[:, :, 0]
    return points, conds


def ray_angles_deg(point: FloatArray, origins: FloatArray, directions: FloatArray) -> FloatArray:
    """(N,) angle in degrees between each ray direction and the vector origin → point ((P, N)
    for (P, 3) points); a point behind a ray (s < 0) gives an angle above 90°."""
    to_point = point[..., None, :] - origins
    to_point /= np.maximum(np.linalg.norm(to_point, axis=-1, keepdims=True), 1e-12)
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    return np.asarray(
        np.degrees(np.arccos(np.clip((to_point * d).sum(axis=-1), -1.0, 1.0))), dtype=np.float64
    )


def ransac_ray_intersection(
    origins: FloatArray,
    directions: FloatArray,
    weights: FloatArray,
    inlier_deg: float,
    min_conditioning: float = 1e-6,
) -> tuple[FloatArray, BoolArray, float]:
    """Robust intersection of rays ``origin + s·direction, s > 0``: every pair of rays (all
    pairs, at once: N is the number of retrieved references, 4950 pairs at 100) proposes a
    point, the one with the largest inlier weight (angle to the ray ≤ ``inlier_deg``, in
    front) wins, the first such pair on a tie, and a weighted least-squares intersection of
    its inliers refines it (twice).

    Returns:
        (3,) point (NaN if no pair is well conditioned), (N,) inlier mask, and the conditioning
        of the final least-squares problem.
    """
    n = origins.shape[0]
    first, second = np.triu_indices(n, k=1)  # every pair, in itertools.combinations' order
    points, conds = _intersect_pairs(origins, directions, first, second)
    inliers = ray_angles_deg(points, origins, directions) <= inlier_deg
    pairs = np.arange(len(first))
    # a pair whose rays meet behind one of its references proposes nothing
    usable = (conds >= min_conditioning) & inliers[pairs, first] & inliers[pairs, second]
    if not usable.any():
        return np.full(3, np.nan), np.zeros(n, dtype=bool), 0.0
    scores = np.where(usable, inliers.astype(np.float64) @ weights, -np.inf)
    point = points[int(np.argmax(scores))]
    cond = 0.0
    for _ in range(2):
        inl = ray_angles_deg(point, origins, directions) <= inlier_deg
        if inl.sum() < 2:
            break
        refined, cond = intersect_rays(origins[inl], directions[inl], weights[inl])
        if not np.all(np.isfinite(refined)):
            break
        point = refined
    inl = ray_angles_deg(point, origins, directions) <= inlier_deg
    return point, inl, cond


def irls_ray_intersection(
    origins: FloatArray,
    directions: FloatArray,
    weights: FloatArray,
    inlier_deg: float,
    iterations: int = 10,
) -> tuple[FloatArray, BoolArray, float]:
    """Robust intersection by iteratively reweighted least squares (Cauchy weights on the ray
    angle, scale ``inlier_deg``), started from the plain weighted least-squares point; rays
    beyond ``inlier_deg`` at the end are outliers and are left out of a final solve."""
    point, cond = intersect_rays(origins, directions, weights)
    if not np.all(np.isfinite(point)):
        return point, np.zeros(origins.shape[0], dtype=bool), cond
    for _ in range(iterations):
        angles = ray_angles_deg(point, origins, directions)
        w = weights / (1.0 + (angles / inlier_deg) ** 2)
        new, cond = intersect_rays(origins, directions, w)
        if not np.all(np.isfinite(new)):
            break
        moved = float(np.linalg.norm(new - point))
        point = new
        if moved < 1e-9:
            break
    inl = ray_angles_deg(point, origins, directions) <= inlier_deg
    if inl.sum() >= 2:
        refined, cond_inl = intersect_rays(origins[inl], directions[inl], weights[inl])
        if np.all(np.isfinite(refined)):
            point, cond = refined, cond_inl
            inl = ray_angles_deg(point, origins, directions) <= inlier_deg
    return point, inl, cond
