"""A localized pose as camera-to-world in the axis conventions of AR and game engines.

The engine's pose is COLMAP's ``cam_from_world`` (camera axes x right, y down, z forward;
the map's world frame as the references define it). Each convention below gives
``world_from_cam`` as a 4×4 matrix ``[[R, p], [0, 1]]`` (column vectors: x_world = R·x_cam + p,
p = the camera position):

- ``colmap``: camera x right, y down, z forward; the map frame as it is.
    M = inverse(cam_from_world)
- ``opengl`` (ARKit, ARCore, WebXR, SceneKit, three.js): camera x right, y up, z backward
  (the camera looks along −z); the map frame as it is (right-handed).
    M_gl = M · F, F = diag(1, −1, −1, 1)
- ``unity``: left-handed; camera x right, y up, z forward; the map frame mirrored along z
  (x_unity = S·x_map, S = diag(1, 1, −1, 1)), the conversion Unity's AR Foundation applies to
  ARKit's and ARCore's right-handed poses.
    M_unity = S · M_gl · S

The map frame is not re-levelled: content authored in map coordinates appears where the map
puts it; a map whose world is y-down (as COLMAP reconstructions often are) stays y-down.
"""

from __future__ import annotations

import numpy as np

from services.geometry.rigid import Rigid3d
from services.types import FloatArray

POSE_CONVENTIONS = ("colmap", "opengl", "unity")

_FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])  # COLMAP camera axes ↔ OpenGL camera axes
_FLIP_Z = np.diag([1.0, 1.0, -1.0, 1.0])  # right-handed ↔ Unity's left-handed


def _homogeneous(pose: Rigid3d) -> FloatArray:
    matrix = np.eye(4)
    matrix[:3, :3] = pose.rotation
    matrix[:3, 3] = pose.translation
    return matrix


def _check(convention: str) -> None:
    if convention not in POSE_CONVENTIONS:
        raise ValueError(
            f"unknown pose convention {convention!r}; known: {', '.join(POSE_CONVENTIONS)}"
        )


def world_from_cam(cam_from_world: Rigid3d, convention: str) -> FloatArray:
    """(4, 4) camera-to-world matrix of ``cam_from_world`` in ``convention``."""
    _check(convention)
    matrix = _homogeneous(cam_from_world.inverse())
    if convention == "colmap":
        return matrix
    matrix = matrix @ _FLIP_YZ
    if convention == "opengl":
        return matrix
    return _FLIP_Z @ matrix @ _FLIP_Z


def cam_from_world_of(world_from_cam_matrix: FloatArray, convention: str) -> Rigid3d:
    """The inverse of ``world_from_cam``: COLMAP ``cam_from_world`` of a (4, 4) camera-to-world
    matrix given in ``convention`` (e.g. a pose an engine reports)."""
    _check(convention)
    matrix = np.asarray(world_from_cam_matrix, np.float64)
    if convention == "unity":
        matrix = _FLIP_Z @ matrix @ _FLIP_Z
    if convention in ("opengl", "unity"):
        matrix = matrix @ _FLIP_YZ
    return Rigid3d(matrix[:3, :3].copy(), matrix[:3, 3].copy()).inverse()
