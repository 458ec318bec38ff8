"""COLMAP camera models (names and parameter order as in COLMAP).

Pixel convention: COLMAP's, the centre of the top-left pixel is at (0.5, 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from services.errors import InvalidInputError
from services.types import FloatArray

# model name -> parameter names, in COLMAP order (pycolmap's ``Camera.params_info``; a test
# checks they agree). Distorted models are undistorted through pycolmap
# (``services.geometry.projection``) before the estimators, which see pinhole cameras.
CAMERA_MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
    "FULL_OPENCV": (
        *("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
        *("k3", "k4", "k5", "k6"),
    ),
    "FOV": ("fx", "fy", "cx", "cy", "omega"),
    "SIMPLE_RADIAL_FISHEYE": ("f", "cx", "cy", "k"),
    "RADIAL_FISHEYE": ("f", "cx", "cy", "k1", "k2"),
    "THIN_PRISM_FISHEYE": (
        *("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
        *("k3", "k4", "sx1", "sy1"),
    ),
    "RAD_TAN_THIN_PRISM_FISHEYE": (
        *("fx", "fy", "cx", "cy", "k0", "k1", "k2", "k3", "k4", "k5"),
        *("p0", "p1", "s0", "s1", "s2", "s3"),
    ),
}
# models whose distortion is none (the pinhole models)
PINHOLE_MODELS = frozenset({"SIMPLE_PINHOLE", "PINHOLE"})


@dataclass(frozen=True)
class Camera:
    """A COLMAP camera: model name, image size in pixels and parameters in COLMAP order."""

    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def __post_init__(self) -> None:
        if self.model not in CAMERA_MODELS:
            raise InvalidInputError(
                f"unknown camera model {self.model!r}; known: {', '.join(CAMERA_MODELS)}"
            )
        expected = CAMERA_MODELS[self.model]
        if len(self.params) != len(expected):
            raise InvalidInputError(
                f"camera model {self.model} takes {len(expected)} params "
                f"({', '.join(expected)}), got {len(self.params)}"
            )
        if self.width <= 0 or self.height <= 0:
            raise InvalidInputError("camera width and height must be positive")
        if not all(np.isfinite(self.params)):
            raise InvalidInputError("camera params must be finite numbers")
        fx, fy = self.focal_lengths
        if fx <= 0 or fy <= 0:
            raise InvalidInputError("camera focal length must be positive")

    @property
    def focal_lengths(self) -> tuple[float, float]:
        names = CAMERA_MODELS[self.model]
        if names[0] == "f":
            return self.params[0], self.params[0]
        return self.params[0], self.params[1]

    @property
    def principal_point(self) -> tuple[float, float]:
        names = CAMERA_MODELS[self.model]
        i = names.index("cx")
        return self.params[i], self.params[i + 1]

    @property
    def distorted(self) -> bool:
        """Whether the model has lens distortion (any model but the pinhole ones)."""
        return self.model not in PINHOLE_MODELS

    @property
    def K(self) -> FloatArray:
        """(3, 3) calibration matrix (distortion ignored)."""
        (fx, fy), (cx, cy) = self.focal_lengths, self.principal_point
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def to_poselib(self) -> dict[str, Any]:
        """Camera dict for PoseLib, which uses the same model names and parameter order."""
        return {
            "model": self.model,
            "width": self.width,
            "height": self.height,
            "params": list(self.params),
        }


# physically plausible intrinsics, relative to the longer image side: a focal length from 0.05×
# (a field of view of about 169°) to 100× (about 0.6°), a principal point within the image
# extended by its size on every side, and distortion coefficients of at most 10 in magnitude
FOCAL_RANGE = (0.05, 100.0)
MAX_DISTORTION = 10.0


def check_plausible(camera: Camera) -> None:
    """Refuse intrinsics no real camera has, which would only mislead the estimators.

    Raises:
        InvalidInputError: naming the parameter and its plausible range.
    """
    side = max(camera.width, camera.height)
    low, high = FOCAL_RANGE[0] * side, FOCAL_RANGE[1] * side
    names = CAMERA_MODELS[camera.model]
    for name, value in zip(names, camera.params, strict=True):
        if name in ("f", "fx", "fy"):
            if not low <= value <= high:
                raise InvalidInputError(
                    f"camera {name} = {value:g} px is implausible: focal lengths lie within "
                    f"{FOCAL_RANGE[0]:g}–{FOCAL_RANGE[1]:g} × the longer image side "
                    f"({low:g}–{high:g} px)"
                )
        elif name in ("cx", "cy"):
            size = camera.width if name == "cx" else camera.height
            if not -size <= value <= 2 * size:
                raise InvalidInputError(
                    f"camera {name} = {value:g} px is implausible: the principal point lies "
                    f"within the image extended by its size ({-size}–{2 * size} px)"
                )
        elif abs(value) > MAX_DISTORTION:
            raise InvalidInputError(
                f"camera {name} = {value:g} is implausible: distortion coefficients lie within "
                f"±{MAX_DISTORTION:g}"
            )


def default_camera(width: int, height: int) -> Camera:
    """Camera assumed for a query that comes without intrinsics: a pinhole with focal length
    1.2 × the longer image side (a ~45° horizontal field of view at 4:3, typical of phone and
    webcam lenses) and the principal point at the image centre."""
    f = 1.2 * max(width, height)
    return Camera("SIMPLE_PINHOLE", width, height, (f, width / 2.0, height / 2.0))
