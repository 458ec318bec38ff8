"""Points from depth, their similarity alignment, and epipolar (Sampson) errors.

With a depth d at a normalised point x̃ = (x, y, 1), the 3D point in the camera frame is d·x̃
(z-depth); ``similarity_from_points`` aligns such point sets (``services.estimators.solvers``
builds the minimal solvers with depth on it).
"""

from __future__ import annotations

import numpy as np

from services.types import FloatArray


def similarity_from_points(
    src: FloatArray, dst: FloatArray, with_scale: bool = True
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Least-squares similarity ``dst ≈ s·R·src + t`` of point sets (Umeyama 1991), batched.

    Args:
        src, dst: (B, n, 3) corresponding points, n ≥ 3.
        with_scale: estimate s; otherwise s = 1 (rigid).
    Returns:
        R (B, 3, 3), t (B, 3), s (B,).
    """
    mu_src = src.mean(axis=1)
    mu_dst = dst.mean(axis=1)
    a = src - mu_src[:, None]
    b = dst - mu_dst[:, None]
    cov = np.einsum("bni,bnj->bij", b, a) / src.shape[1]
    # a sample with a non-finite point gets a NaN transform (its SVD would not converge)
    finite = np.isfinite(cov).all(axis=(1, 2))
    U, S, Vt = np.linalg.svd(np.where(finite[:, None, None], cov, np.eye(3)))
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    D = np.ones((src.shape[0], 3))
    D[:, 2] = d
    R = np.where(finite[:, None, None], (U * D[:, None, :]) @ Vt, np.nan)
    if with_scale:
        var_src = (a * a).sum(axis=(1, 2)) / src.shape[1]
        s = (S * D).sum(axis=1) / np.maximum(var_src, 1e-300)
    else:
        s = np.ones(src.shape[0])
    t = mu_dst - s[:, None] * np.einsum("bij,bj->bi", R, mu_src)
    return R, t, s


def back_project(normalized: FloatArray, depth: FloatArray) -> FloatArray:
    """(…, 2) normalised points and (…,) z-depths → (…, 3) camera-frame points."""
    return (
        np.concatenate([normalized, np.ones((*normalized.shape[:-1], 1))], axis=-1)
        * depth[..., None]
    )


def skew(v: FloatArray) -> FloatArray:
    """(..., 3) → (..., 3, 3) cross-product matrices."""
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def sampson_errors(
    R: FloatArray, t: FloatArray, x_src: FloatArray, x_dst: FloatArray
) -> FloatArray:
    """Sampson epipolar error (normalised units, ≈ pixel error / focal) of relative poses.

    Args:
        R, t: (B, 3, 3), (B, 3) ``dst_from_src`` hypotheses (the length of t is irrelevant).
        x_src, x_dst: (N, 2) normalised correspondences.
    Returns:
        (B, N) errors.
    """
    E = skew(t) @ R
    x1, y1 = x_src[None, :, 0], x_src[None, :, 1]
    x2, y2 = x_dst[None, :, 0], x_dst[None, :, 1]
    e = E[:, :, :, None]  # (B, 3, 3, 1) broadcasts against (1, N)
    Ex1_0 = e[:, 0, 0] * x1 + e[:, 0, 1] * y1 + e[:, 0, 2]
    Ex1_1 = e[:, 1, 0] * x1 + e[:, 1, 1] * y1 + e[:, 1, 2]
    Ex1_2 = e[:, 2, 0] * x1 + e[:, 2, 1] * y1 + e[:, 2, 2]
    Etx2_0 = e[:, 0, 0] * x2 + e[:, 1, 0] * y2 + e[:, 2, 0]
    Etx2_1 = e[:, 0, 1] * x2 + e[:, 1, 1] * y2 + e[:, 2, 1]
    num = Ex1_0 * x2 + Ex1_1 * y2 + Ex1_2
    den = Ex1_0**2 + Ex1_1**2 + Etx2_0**2 + Etx2_1**2
    return np.asarray(np.abs(num) / np.sqrt(np.maximum(den, 1e-300)), dtype=np.float64)
