"""Gravity directions: the map's down from its references, a pose's disagreement with a
measured gravity, and the quarter turn that brings an image upright.

Directions are unit (3,) vectors pointing down (towards the earth), in the frame named;
camera frames use COLMAP axes (x right, y down, z forward).
"""

from __future__ import annotations

import numpy as np

from services.geometry.intrinsics_adaptation import QUARTER_TURNS, rotated_from_camera
from services.geometry.rigid import Rigid3d
from services.types import FloatArray

# below this tilt of gravity out of the optical axis (camera looking almost straight down or
# up) the image has no upright orientation
MIN_IN_PLANE_TILT_DEG = 20.0


def unit(vector: FloatArray) -> FloatArray:
    """``vector`` / its norm, for any finite non-zero length: the vector is first scaled by
    its largest component, so that neither 1e300 (whose square overflows) nor 1e-300 (whose
    square underflows to 0) is refused.

    Raises:
        ValueError: a zero or non-finite vector.
    """
    v = np.asarray(vector, np.float64).reshape(3)
    largest = float(np.max(np.abs(v)))
    if not np.isfinite(largest) or largest == 0.0:
        raise ValueError("a direction must be a finite, non-zero vector")
    scaled = v / largest
    out: FloatArray = scaled / np.linalg.norm(scaled)
    return out


def references_down(cams_from_world: list[Rigid3d]) -> FloatArray:
    """World down as the references' mean image down (their camera +y axis in the world):
    right when the references were captured roughly upright, as mapping apps and scanners do
    (pitch and roll then average out).

    Raises:
        ValueError: no references, or their downs cancel out.
    """
    if not cams_from_world:
        raise ValueError("no references")
    downs = np.stack([pose.rotation[1] for pose in cams_from_world])  # R.T @ (0, 1, 0)
    return unit(downs.mean(axis=0))


def gravity_error_deg(
    cam_from_world: Rigid3d, gravity_cam: FloatArray, world_down: FloatArray
) -> float:
    """Angle in degrees between the measured gravity (camera frame) and the world's down
    seen from the pose ``cam_from_world``."""
    predicted = cam_from_world.rotation @ unit(world_down)
    cos = float(np.clip(predicted @ unit(gravity_cam), -1.0, 1.0))
    return float(np.degrees(np.arccos(cos)))


def upright_turn(gravity_cam: FloatArray) -> int | None:
    """The clockwise quarter turn of the image after which gravity points down in it (closest
    to +y); None when gravity lies within ``MIN_IN_PLANE_TILT_DEG`` of the optical axis."""
    g = unit(gravity_cam)
    if np.hypot(g[0], g[1]) < np.sin(np.radians(MIN_IN_PLANE_TILT_DEG)):
        return None
    downs = [float((rotated_from_camera(turn) @ g)[1]) for turn in QUARTER_TURNS]
    return QUARTER_TURNS[int(np.argmax(downs))]
