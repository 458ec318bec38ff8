"""Pixels ↔ normalised image coordinates ↔ camera rays, for every COLMAP camera model.

Pixel convention: COLMAP's (centre of the top-left pixel at (0.5, 0.5)), as everywhere in the
engine. Pinhole models take a numpy fast path; distorted models go through pycolmap, which
also undistorts keypoints onto an equivalent pinhole camera (``undistort_to_pinhole``) for the
estimators.
"""

from __future__ import annotations

import math

import numpy as np
import pycolmap

from services.geometry.camera import PINHOLE_MODELS, Camera
from services.types import BoolArray, FloatArray

_PINHOLE_MODELS = PINHOLE_MODELS
# undistorted keypoints are kept up to this angle off the optical axis (a pinhole image
# plane cannot hold a fisheye's rays at 90° and beyond, and stretches those close to it)
MAX_UNDISTORTED_ANGLE_DEG = 85.0
# an undistorted keypoint is kept when distorting it again lands within this many pixels of
# where it was (pycolmap's iterative inversion does not converge far outside the image)
ROUND_TRIP_PX = 0.1


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


def pinhole_of(camera: Camera) -> Camera:
    """The pinhole camera with ``camera``'s focal lengths, principal point and size (``camera``
    itself when it has no distortion)."""
    if not camera.distorted:
        return camera
    (fx, fy), (cx, cy) = camera.focal_lengths, camera.principal_point
    return Camera("PINHOLE", camera.width, camera.height, (fx, fy, cx, cy))


def undistort_to_pinhole(camera: Camera, xy: FloatArray) -> tuple[Camera, FloatArray, BoolArray]:
    """Pixels of ``camera`` moved to where ``pinhole_of(camera)`` sees the same rays, through
    pycolmap's model of the camera (``Camera.cam_from_img``).

    Args:
        xy: (N, 2) pixel coordinates, COLMAP convention.
    Returns:
        the pinhole camera, (N, 2) float64 undistorted pixels and an (N,) mask of those kept:
        finite, within ``MAX_UNDISTORTED_ANGLE_DEG`` of the optical axis and distorting back
        to the input within ``ROUND_TRIP_PX`` (the others' coordinates are meaningless).
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    pinhole = pinhole_of(camera)
    if pinhole is camera:
        return camera, xy, np.ones(xy.shape[0], dtype=bool)
    normalized = normalized_from_pixels(camera, xy)
    with np.errstate(invalid="ignore"):
        kept = np.all(np.isfinite(normalized), axis=1) & (
            np.linalg.norm(normalized, axis=1) <= math.tan(math.radians(MAX_UNDISTORTED_ANGLE_DEG))
        )
    if kept.any():
        again = pixels_from_camera_points(camera, homogeneous(normalized[kept]))
        with np.errstate(invalid="ignore"):
            close = np.linalg.norm(again - xy[kept], axis=1) <= ROUND_TRIP_PX
        kept[np.flatnonzero(kept)[~close]] = False
    (fx, fy), (cx, cy) = pinhole.focal_lengths, pinhole.principal_point
    out = normalized * np.array([fx, fy]) + np.array([cx, cy])
    out[~kept] = np.array([cx, cy])
    return pinhole, out, kept


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
