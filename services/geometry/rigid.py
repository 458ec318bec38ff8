"""Rigid transforms ``<dst>_from_<src>`` with quaternions in ``[w, x, y, z]`` order.

A ``Rigid3d`` maps points as ``x_dst = R @ x_src + t``. Camera poses are ``cam_from_world``;
the camera centre in world coordinates is ``C = -R.T @ t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.types import FloatArray


def quaternion_to_matrix(q: FloatArray) -> FloatArray:
    """Rotation matrix of a unit quaternion.

    Args:
        q: (4,) quaternion ``[w, x, y, z]``; normalised here.
    Returns:
        (3, 3) rotation matrix.
    """
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(R: FloatArray) -> FloatArray:
    """Unit quaternion ``[w, x, y, z]`` (w >= 0) of a (3, 3) rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    trace = np.trace(R)
    diag = np.diag(R)
    k = int(np.argmax([trace, *diag]))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    qa = np.asarray(q)
    qa /= np.linalg.norm(qa)
    return qa if qa[0] >= 0 else -qa


# a stored camera pose is at most this far from its map's origin (|translation| of
# ``cam_from_world`` is the camera centre's distance from it): about the Earth's diameter, so
# that even a map in Earth-centred coordinates fits, while magnitudes whose squares overflow
# (1e155 and up) never reach the estimators
MAX_TRANSLATION_M = 1e7
# a quaternion is normalised when read; farther than this from unit norm it is refused
QUATERNION_NORM_TOLERANCE = 1e-3


def pose_problem(quaternion: FloatArray, translation: FloatArray) -> str | None:
    """Why a camera pose ``[w, x, y, z]``, ``t`` cannot be stored, or None when it can: every
    number finite, a unit quaternion (within ``QUATERNION_NORM_TOLERANCE``) and
    ``|t| <= MAX_TRANSLATION_M``."""
    q = np.asarray(quaternion, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    if q.shape != (4,) or t.shape != (3,):
        return "a pose is a quaternion of 4 numbers and a translation of 3"
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))):
        return "pose values must be finite numbers"
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        return f"rotation must be a unit quaternion (norm {norm:.6g})"
    with np.errstate(over="ignore"):  # a square may overflow to inf: beyond the range
        distance = float(np.linalg.norm(t))
    if not distance <= MAX_TRANSLATION_M:
        return (
            f"|translation| = {distance:.6g} m is beyond the physical range: a camera lies "
            f"within {MAX_TRANSLATION_M:g} m of its map's origin"
        )
    return None


@dataclass(frozen=True)
class Rigid3d:
    """``x_dst = rotation @ x_src + translation``.

    Attributes:
        rotation: (3, 3) float64 rotation matrix.
        translation: (3,) float64 translation.
    """

    rotation: FloatArray
    translation: FloatArray

    @classmethod
    def from_quaternion(cls, q: FloatArray, t: FloatArray) -> Rigid3d:
        return cls(quaternion_to_matrix(np.asarray(q)), np.asarray(t, dtype=np.float64).reshape(3))

    @classmethod
    def identity(cls) -> Rigid3d:
        return cls(np.eye(3), np.zeros(3))

    @property
    def quaternion(self) -> FloatArray:
        """(4,) ``[w, x, y, z]``."""
        return matrix_to_quaternion(self.rotation)

    def inverse(self) -> Rigid3d:
        Rt = self.rotation.T
        return Rigid3d(Rt, -Rt @ self.translation)

    def compose(self, other: Rigid3d) -> Rigid3d:
        """``self ∘ other``: apply ``other`` first (``a_from_c = a_from_b.compose(b_from_c)``)."""
        return Rigid3d(
            self.rotation @ other.rotation,
            self.rotation @ other.translation + self.translation,
        )

    def apply(self, points: FloatArray) -> FloatArray:
        """Transform (N, 3) points."""
        return np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation

    @property
    def center(self) -> FloatArray:
        """(3,) origin of the destination frame in source coordinates, ``-R.T @ t``; for
        ``cam_from_world`` this is the camera centre in world coordinates."""
        return -self.rotation.T @ self.translation

    @property
    def matrix(self) -> FloatArray:
        """(3, 4) ``[R | t]``."""
        return np.hstack([self.rotation, self.translation[:, None]])


def rotation_error_deg(R_a: FloatArray, R_b: FloatArray) -> float:
    """Angle in degrees of ``R_a @ R_b.T``."""
    cos = (np.trace(np.asarray(R_a) @ np.asarray(R_b).T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def pose_error(estimate: Rigid3d, truth: Rigid3d) -> tuple[float, float]:
    """(camera-centre distance in world units, rotation angle in degrees) between two
    ``cam_from_world`` poses."""
    return (
        float(np.linalg.norm(estimate.center - truth.center)),
        rotation_error_deg(estimate.rotation, truth.rotation),
    )
