"""Device poses from an AR session (ARKit ``ARFrame.camera.transform``, ARCore
``Camera.getPose()``, WebXR ``XRView.transform``) as the engine's ``cam_from_session``.

An AR session reports ``session_from_camera`` (camera-to-session) with OpenGL camera axes:
x right, y up, z backward (the camera looks along −z). The engine's cameras use COLMAP's axes:
x right, y down, z forward. A point with COLMAP camera coordinates ``x_cv`` has OpenGL
camera coordinates ``x_gl = F · x_cv`` with ``F = diag(1, −1, −1)``, so

    session_from_camera_cv = (R_gl · F, t)    and    cam_from_session = its inverse.

Session units are metres (ARKit, ARCore and WebXR all track metrically).
"""

from __future__ import annotations

import numpy as np

from services.errors import InvalidInputError
from services.geometry.rigid import Rigid3d
from services.types import FloatArray

# COLMAP camera axes → OpenGL camera axes (y and z flipped); its own inverse
OPENGL_FROM_COLMAP_CAMERA = np.diag([1.0, -1.0, -1.0])

# a rotation block is accepted when ‖RᵀR − I‖ and |det R − 1| stay within this (float32
# matrices from a device carry ~1e-7 error; a scaled or sheared matrix is far outside)
ROTATION_TOLERANCE = 1e-3


def rigid_from_matrix(matrix: FloatArray, name: str = "matrix") -> Rigid3d:
    """The rigid transform of a (4, 4) homogeneous matrix ``[[R, t], [0, 0, 0, 1]]``.

    The rotation block is re-orthonormalised (nearest rotation, by SVD) after the check.

    Raises:
        InvalidInputError: not 4×4, not finite, last row not (0, 0, 0, 1), or the 3×3 block
            not a rotation (scale, shear or reflection), naming ``name``.
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise InvalidInputError(f"{name} must be 4×4, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise InvalidInputError(f"{name} must hold finite numbers")
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        raise InvalidInputError(f"{name}: the last row must be [0, 0, 0, 1] (row-major order)")
    rotation = m[:3, :3]
    orthogonality = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    determinant = float(np.linalg.det(rotation))
    if orthogonality > ROTATION_TOLERANCE or abs(determinant - 1.0) > ROTATION_TOLERANCE:
        raise InvalidInputError(
            f"{name}: the upper-left 3×3 block is not a rotation (‖RᵀR − I‖ = "
            f"{orthogonality:.3g}, det = {determinant:.6g}); scale, shear and mirroring are "
            "not allowed"
        )
    u, _, vt = np.linalg.svd(rotation)
    return Rigid3d(u @ vt, m[:3, 3].copy())


def homogeneous(pose: Rigid3d) -> FloatArray:
    """(4, 4) row-major homogeneous matrix of ``pose``."""
    out = np.eye(4)
    out[:3, :3] = pose.rotation
    out[:3, 3] = pose.translation
    return out


def cam_from_session(session_from_camera_opengl: Rigid3d) -> Rigid3d:
    """The engine's ``cam_from_session`` (COLMAP camera axes) from an AR session's
    camera-to-session pose with OpenGL camera axes (ARKit ``camera.transform``)."""
    session_from_cam = Rigid3d(
        session_from_camera_opengl.rotation @ OPENGL_FROM_COLMAP_CAMERA,
        session_from_camera_opengl.translation,
    )
    return session_from_cam.inverse()


def session_from_camera_opengl(cam_from_session_colmap: Rigid3d) -> Rigid3d:
    """The inverse of ``cam_from_session``: an AR session's camera-to-session pose with OpenGL
    camera axes from the engine's ``cam_from_session``."""
    session_from_cam = cam_from_session_colmap.inverse()
    return Rigid3d(
        session_from_cam.rotation @ OPENGL_FROM_COLMAP_CAMERA, session_from_cam.translation
    )
