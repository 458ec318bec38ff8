"""Intrinsics given for another image size or orientation, adapted to the uploaded image.

Phones give intrinsics for the full-resolution sensor image in its native (landscape)
orientation, while apps upload a downscaled and often portrait image. An upload made from the
camera's image by a quarter-turn rotation and a (near) uniform resize has exactly known
intrinsics; this module computes them.

Pixel convention: COLMAP's (the top-left pixel's centre at (0.5, 0.5)), so a W×H image spans
[0, W] × [0, H] in continuous coordinates and both operations map image edges to image edges:

- resize from W×H to W'×H' (sx = W'/W, sy = H'/H): x' = sx·x, y' = sy·y, hence
  fx' = sx·fx, fy' = sy·fy, cx' = sx·cx, cy' = sy·cy; distortion acts on normalized
  coordinates and is unchanged.
- rotation clockwise (as displayed) of a W×H image:
    90°:  (x', y') = (H − y, x)      fx' = fy, fy' = fx, cx' = H − cy, cy' = cx
    180°: (x', y') = (W − x, H − y)  fx' = fx, fy' = fy, cx' = W − cx, cy' = H − cy
    270°: (x', y') = (y, W − x)      fx' = fy, fy' = fx, cx' = cy,     cy' = W − cx
  The rotated camera is the same camera turned about its optical axis: a point X in the
  camera frame is ``R_z(rotation) @ X`` in the rotated one (``rotated_from_camera``), radial
  distortion is unchanged and the tangential and thin-prism terms turn with the image, e.g.
  OPENCV's (p1', p2') = (p2, −p1) at 90°, (−p1, −p2) at 180°, (−p2, p1) at 270°
  (``_quarter_turn_distortion`` for every model).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.errors import InvalidInputError
from services.geometry.camera import CAMERA_MODELS, Camera
from services.types import FloatArray

QUARTER_TURNS = (0, 90, 180, 270)

# how far, in upload pixels, the upload's size may be from an exact uniform scale of the
# camera's (rounding of a resize)
SIZE_TOLERANCE_PX = 1.0
# the largest resize factor either way between the camera's image and the upload
MAX_SCALE_RATIO = 64.0

# a model with one focal length and its equivalent with two, for resizes that are not exactly
# uniform: SIMPLE_RADIAL's and RADIAL's distortion is OPENCV's with the other terms zero, and
# SIMPLE_RADIAL_FISHEYE's and RADIAL_FISHEYE's OPENCV_FISHEYE's
_TWO_FOCAL_MODEL = {
    "SIMPLE_PINHOLE": "PINHOLE",
    "SIMPLE_RADIAL": "OPENCV",
    "RADIAL": "OPENCV",
    "SIMPLE_RADIAL_FISHEYE": "OPENCV_FISHEYE",
    "RADIAL_FISHEYE": "OPENCV_FISHEYE",
}


@dataclass(frozen=True)
class CameraAdaptation:
    """How a request's camera was turned into the upload's.

    Attributes:
        camera: the intrinsics of the upload as decoded (EXIF orientation applied).
        rotation_deg: clockwise quarter turn from the given camera's image to the upload.
        scale: (sx, sy), upload pixels per pixel of the rotated camera image, along x and y.
        exif_orientation: the upload's EXIF orientation tag (1–8), None without one.
    """

    camera: Camera
    rotation_deg: int
    scale: tuple[float, float]
    exif_orientation: int | None = None

    @property
    def identity(self) -> bool:
        return self.rotation_deg == 0 and self.scale == (1.0, 1.0)


def _check_rotation(rotation_deg: int) -> None:
    if rotation_deg not in QUARTER_TURNS:
        raise ValueError(f"rotation must be one of {QUARTER_TURNS} degrees, got {rotation_deg}")


def rotated_size(width: int, height: int, rotation_deg: int) -> tuple[int, int]:
    """(width, height) of a width×height image rotated by ``rotation_deg``."""
    _check_rotation(rotation_deg)
    return (height, width) if rotation_deg in (90, 270) else (width, height)


def rotate_points(xy: FloatArray, rotation_deg: int, width: int, height: int) -> FloatArray:
    """Pixel coordinates in a width×height image → the same points in the image rotated
    clockwise by ``rotation_deg`` (formulas in the module docstring).

    Args:
        xy: (N, 2) COLMAP pixel coordinates.

    Returns:
        (N, 2) float64 coordinates in the rotated image.
    """
    _check_rotation(rotation_deg)
    x, y = np.asarray(xy, np.float64).T
    if rotation_deg == 90:
        return np.stack([height - y, x], axis=-1)
    if rotation_deg == 180:
        return np.stack([width - x, height - y], axis=-1)
    if rotation_deg == 270:
        return np.stack([y, width - x], axis=-1)
    return np.stack([x, y], axis=-1)


def rotated_from_camera(rotation_deg: int) -> FloatArray:
    """(3, 3) rotation taking camera-frame points into the frame of the camera whose image
    is turned clockwise by ``rotation_deg`` (x right, y down, z forward in both)."""
    _check_rotation(rotation_deg)
    c, s = {0: (1, 0), 90: (0, 1), 180: (-1, 0), 270: (0, -1)}[rotation_deg]
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotate_camera(camera: Camera, rotation_deg: int) -> Camera:
    """The intrinsics of ``camera``'s image rotated clockwise by ``rotation_deg``."""
    _check_rotation(rotation_deg)
    if rotation_deg == 0:
        return camera
    names = CAMERA_MODELS[camera.model]
    values = dict(zip(names, camera.params, strict=True))
    width, height = rotated_size(camera.width, camera.height, rotation_deg)
    (cx, cy) = camera.principal_point
    new_cx, new_cy = rotate_points(np.array([[cx, cy]]), rotation_deg, camera.width, camera.height)[
        0
    ]
    for _ in range(rotation_deg // 90):
        _quarter_turn_distortion(camera.model, values)
    values["cx"], values["cy"] = float(new_cx), float(new_cy)
    return Camera(camera.model, width, height, tuple(values[name] for name in names))


def _quarter_turn_distortion(model: str, values: dict[str, float]) -> None:
    """Turn the focal lengths and the non-radial distortion terms of ``values`` by 90°
    clockwise, in place: the distortion's displacement turns with the image, (dx, dy) →
    (−dy, dx). Radial terms are unchanged. (A test checks every model against pycolmap.)"""
    if "fx" in values:
        values["fx"], values["fy"] = values["fy"], values["fx"]
    if model == "RAD_TAN_THIN_PRISM_FISHEYE":
        values["p0"], values["p1"] = -values["p1"], values["p0"]
        s0, s1, s2, s3 = (values[f"s{i}"] for i in range(4))
        values["s0"], values["s1"], values["s2"], values["s3"] = -s2, -s3, s0, s1
    elif "p1" in values:  # OPENCV, FULL_OPENCV, THIN_PRISM_FISHEYE
        values["p1"], values["p2"] = values["p2"], -values["p1"]
    if "sx1" in values:  # THIN_PRISM_FISHEYE
        values["sx1"], values["sy1"] = -values["sy1"], values["sx1"]


def scale_camera(camera: Camera, width: int, height: int) -> Camera:
    """The intrinsics of ``camera``'s image resized to width×height (edges onto edges). A model
    with one focal length becomes its two-focal equivalent when the resize is not uniform."""
    sx, sy = width / camera.width, height / camera.height
    model = camera.model
    values = dict(zip(CAMERA_MODELS[model], camera.params, strict=True))
    if sx != sy and model in _TWO_FOCAL_MODEL:
        model = _TWO_FOCAL_MODEL[model]
        values = {
            "fx": values["f"],
            "fy": values["f"],
            "k1": values.get("k", 0.0),  # the single-term models' k is k1
            **values,
        }
        values = {name: values.get(name, 0.0) for name in CAMERA_MODELS[model]}
    scales = {"f": sx, "fx": sx, "cx": sx, "fy": sy, "cy": sy}
    names = CAMERA_MODELS[model]
    return Camera(model, width, height, tuple(values[n] * scales.get(n, 1.0) for n in names))


def uniform_scale(
    size: tuple[int, int], target: tuple[int, int], tolerance_px: float = SIZE_TOLERANCE_PX
) -> tuple[float, float] | None:
    """(sx, sy) taking ``size`` (width, height) to ``target`` when that is one uniform scale
    up to ``tolerance_px`` target pixels on either side, else None."""
    (w, h), (tw, th) = size, target
    sx, sy = tw / w, th / h
    if not 1.0 / MAX_SCALE_RATIO <= sx <= MAX_SCALE_RATIO:
        return None
    if abs(sx * h - th) > tolerance_px or abs(sy * w - tw) > tolerance_px:
        return None
    return sx, sy


def _turned_size(camera: Camera, turn: int) -> tuple[int, int]:
    """(width, height) of ``camera``'s image turned by ``turn`` degrees."""
    return (camera.height, camera.width) if turn % 180 else (camera.width, camera.height)


def adapt_camera(
    camera: Camera,
    upload_size: tuple[int, int],
    exif_rotation_deg: int = 0,
    exif_orientation: int | None = None,
    rotation_deg: int | None = None,
) -> CameraAdaptation:
    """The intrinsics of the upload (``upload_size`` = (width, height) as decoded, EXIF
    orientation applied) from ``camera``, given for the image the upload was made from by a
    clockwise quarter turn and a uniform resize.

    Args:
        exif_rotation_deg: the clockwise turn the upload's EXIF orientation applied on decode.
        rotation_deg: the clockwise turn from the camera's image to the decoded upload, when
            the client states it. Otherwise the sizes decide it up to a half turn, relative to
            the upload's stored pixels (before EXIF): no turn when the camera's aspect matches
            theirs, else 90° clockwise (a phone held upright: its landscape sensor image
            turned to portrait); the EXIF turn is then added.

    Raises:
        InvalidInputError: no such turn and scale relate the sizes; the message lists the
            camera sizes that would be accepted.
    """
    if rotation_deg is not None:
        candidates = [rotation_deg]
    else:
        candidates = [(turn + exif_rotation_deg) % 360 for turn in (0, 90)]
    for turn in candidates:
        rotated = rotate_camera(camera, turn)
        scale = uniform_scale((rotated.width, rotated.height), upload_size)
        if scale is not None:
            adapted = scale_camera(rotated, *upload_size) if scale != (1.0, 1.0) else rotated
            return CameraAdaptation(adapted, turn, scale, exif_orientation)
    w, h = upload_size
    exif = f", EXIF orientation {exif_orientation}" if exif_orientation not in (None, 1) else ""
    turn_text = (
        f"turned by camera_rotation_deg = {rotation_deg}° "
        if rotation_deg is not None
        else "possibly turned by a quarter turn "
    )
    accepted = f"{w}×{h}" if rotation_deg in (None, 0, 180) else f"{h}×{w}"
    if rotation_deg is None:
        accepted += f" or {h}×{w}"
    fitting = [
        turn
        for turn in (0, 90)
        if uniform_scale(_turned_size(camera, turn), upload_size) is not None
    ]
    if rotation_deg is not None and fitting:
        # the sizes fit: the stated turn is what disagrees
        tw, th = _turned_size(camera, rotation_deg)
        fits = "unturned (or half turned)" if fitting[0] == 0 else "a quarter turned"
        problem = (
            f"camera is {camera.width}×{camera.height} and the image {w}×{h} (as decoded"
            f"{exif}): they fit {fits}, but camera_rotation_deg = {rotation_deg}° turns the "
            f"camera's image to {tw}×{th}"
        )
    else:
        problem = (
            f"camera is {camera.width}×{camera.height} but the image is {w}×{h} (as decoded"
            f"{exif}), a size the camera fits neither as it is nor turned a quarter"
        )
    raise InvalidInputError(
        f"{problem}; the camera must describe the image the upload was made from, {turn_text}and "
        f"resized uniformly (within {SIZE_TOLERANCE_PX:g} px): a camera of {accepted} "
        f"or a multiple of it (e.g. ×2, ×3) is accepted"
    )
