"""Pixels ↔ normalised image coordinates ↔ camera rays, for every COLMAP camera model.

Pixel convention: COLMAP's (centre of the top-left pixel at (0.5, 0.5)), as everywhere in the
engine. Pinhole models take a numpy fast path; distorted models go through pycolmap.
"""

from __future__ import annotations

import numpy as np
import pycolmap

from services.geometry.camera import Camera
from services.types import FloatArray

_PINHOLE_MODELS = frozenset({"SIMPLE_PINHOLE", "PINHOLE"})


def _pycolmap_camera(camera: Camera) -> pycolmap.Camera:
    return pycolmap.Camera(
        model=camera.model,
        width=camera.width,
        height=camera.height,
        params=list(camera.params),
    )


def normalized_from_pixels(camera: Camera, xy: FloatArray) -> FloatArray:
    """Undistorted normalised coordinates (x/z, y/z) of pixels.

    Args:
        xy: (N, 2) pixel coordinates, COLMAP convention.
    Returns:
        (N, 2) float64.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if camera.model in _PINHOLE_MODELS or xy.shape[0] == 0:
        (fx, fy), (cx, cy) = camera.focal_lengths, camera.principal_point
        return np.asarray((xy - np.array([cx, cy])) / np.array([fx, fy]), dtype=np.float64)
    out = _pycolmap_camera(camera).cam_from_img(np.ascontiguousarray(xy))
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def homogeneous(xy: FloatArray) -> FloatArray:
    """(N, 2) → (N, 3) by appending ones."""
    return np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)


def pixels_from_camera_points(camera: Camera, points_cam: FloatArray) -> FloatArray:
    """Project (N, 3) camera-frame points to (N, 2) pixels (NaN where z <= 0)."""
    points_cam = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    z = points_cam[:, 2:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        normalized = np.where(z > 0, points_cam[:, :2] / z, np.nan)
    if camera.model in _PINHOLE_MODELS or points_cam.shape[0] == 0:
        (fx, fy), (cx, cy) = camera.focal_lengths, camera.principal_point
        return np.asarray(normalized * np.array([fx, fy]) + np.array([cx, cy]), dtype=np.float64)
    ok = np.all(np.isfinite(normalized), axis=1)
    out = np.full((points_cam.shape[0], 2), np.nan)
    if ok.any():
        cam_points = homogeneous(normalized[ok])
        out[ok] = _pycolmap_camera(camera).img_from_cam(cam_points, check_cheirality=False)
    return out


def mean_focal(camera: Camera) -> float:
    """Mean of the focal lengths in pixels: converts normalised errors to approximate pixels."""
    fx, fy = camera.focal_lengths
    return 0.5 * (fx + fy)
