"""A map's geo-registration: the similarity ``enu_from_map`` that takes map coordinates to
metres in a local East-North-Up frame anchored at a WGS84 origin, set by hand or estimated
robustly from reference camera centres that carry GPS positions."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pycolmap

from services.errors import InvalidInputError
from services.geo.geodesy import HEIGHT_RANGE_M, Geodetic, enu_from_geodetic, geodetic_from_enu
from services.geometry.rigid import matrix_to_quaternion, quaternion_to_matrix
from services.types import BoolArray, FloatArray

MIN_GPS_REFERENCES = 3
# the RANSAC inlier threshold of an estimate, in metres between a registered camera centre and
# its GPS position, when none is given (about 3 × a phone's GPS accuracy outdoors)
DEFAULT_MAX_ERROR_M = 10.0
# the smallest singular value (relative to the largest) of the centred map centres below
# which their layout is a line and the rotation about it is unobservable
COLLINEAR_RATIO = 1e-3
# an estimated registration whose orientation the GPS positions fix worse than this (1-σ) is
# refused: the references span too little against the GPS scatter for a usable heading
MAX_ROTATION_SIGMA_DEG = 20.0
# physical ranges of a registration besides its origin's height (HEIGHT_RANGE_M): the scale in
# metres per map unit, and |translation| of enu_from_map in metres (about the Earth's
# diameter: beyond it ENU at the origin means nothing)
SCALE_RANGE = (1e-6, 1e6)
MAX_ENU_TRANSLATION_M = 1e7


def height_problem(height: float, what: str) -> str | None:
    """Why ``height`` (metres above the WGS84 ellipsoid) is no physical one, or None."""
    low, high = HEIGHT_RANGE_M
    if not (np.isfinite(height) and low <= height <= high):
        return f"{what} {height:g} m is out of the physical range {low:g}…{high:g} m"
    return None


@dataclass(frozen=True)
class GeoRegistration:
    """``x_enu = scale · rotation · x_map + translation`` (metres, ENU at ``origin``).

    Attributes:
        rotation: (3, 3) enu_from_map rotation.
        translation: (3,) metres.
        scale: metres per map unit.
        position_sigma_m: 1-σ of a registered position from the registration alone (0 when
            set by hand: its error is the admin's).
        rotation_sigma_deg: 1-σ of a registered orientation from the registration alone.
    """

    origin: Geodetic
    rotation: FloatArray
    translation: FloatArray
    scale: float
    position_sigma_m: float = 0.0
    rotation_sigma_deg: float = 0.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise InvalidInputError("the registration's scale must be a positive number")
        if not SCALE_RANGE[0] <= self.scale <= SCALE_RANGE[1]:
            raise InvalidInputError(
                f"the registration's scale {self.scale:g} m per map unit is out of the "
                f"physical range {SCALE_RANGE[0]:g}…{SCALE_RANGE[1]:g}"
            )
        if not -90.0 <= self.origin.latitude <= 90.0:
            raise InvalidInputError("the origin's latitude must be within [-90, 90] degrees")
        if not -180.0 <= self.origin.longitude <= 180.0:
            raise InvalidInputError("the origin's longitude must be within [-180, 180] degrees")
        problem = height_problem(self.origin.height, "the origin's height")
        if problem is not None:
            raise InvalidInputError(problem)
        translation = np.asarray(self.translation, np.float64)
        if not np.all(np.isfinite(translation)) or not (
            np.max(np.abs(translation)) <= MAX_ENU_TRANSLATION_M
            and float(np.linalg.norm(translation)) <= MAX_ENU_TRANSLATION_M
        ):
            raise InvalidInputError(
                f"the registration's |translation| is out of the physical range: at most "
                f"{MAX_ENU_TRANSLATION_M:g} m"
            )
        if not (
            np.all(np.isfinite(self.rotation))
            and np.isfinite(self.position_sigma_m)
            and np.isfinite(self.rotation_sigma_deg)
        ):
            raise InvalidInputError("the registration's values must be finite numbers")

    @classmethod
    def from_quaternion(
        cls,
        origin: Geodetic,
        q_wxyz: FloatArray,
        translation: FloatArray,
        scale: float,
        position_sigma_m: float = 0.0,
        rotation_sigma_deg: float = 0.0,
    ) -> GeoRegistration:
        """Raises:
        InvalidInputError: a zero quaternion, a non-positive scale, an origin off the globe.
        """
        q = np.asarray(q_wxyz, np.float64)
        norm = float(np.linalg.norm(q))
        if not np.isfinite(norm) or norm < 1e-9:
            raise InvalidInputError("the registration's rotation quaternion is zero")
        return cls(
            origin,
            quaternion_to_matrix(q / norm),
            np.asarray(translation, np.float64).reshape(3),
            scale,
            position_sigma_m,
            rotation_sigma_deg,
        )

    @property
    def quaternion(self) -> FloatArray:
        """enu_from_map rotation as [w, x, y, z]."""
        return matrix_to_quaternion(self.rotation)

    def enu_from_map(self, points: FloatArray) -> FloatArray:
        """(N, 3) map points → (N, 3) ENU metres."""
        return self.scale * np.atleast_2d(points) @ self.rotation.T + self.translation

    def map_from_enu(self, enu: FloatArray) -> FloatArray:
        """(N, 3) ENU metres → (N, 3) map points."""
        return (np.atleast_2d(enu) - self.translation) @ self.rotation / self.scale

    def geodetic_from_map(self, points: FloatArray) -> FloatArray:
        """(N, 3) map points → (N, 3) [latitude°, longitude°, height m]."""
        return geodetic_from_enu(self.enu_from_map(points), self.origin)

    def map_from_geodetic(self, lat_lon_h: FloatArray) -> FloatArray:
        """(N, 3) geodetic points → (N, 3) map points."""
        return self.map_from_enu(enu_from_geodetic(lat_lon_h, self.origin))

    def map_up(self) -> FloatArray:
        """The local vertical (ENU up) as a unit direction in the map frame."""
        return np.asarray(self.rotation[2], np.float64)  # Rᵀ·(0, 0, 1)


@dataclass(frozen=True)
class RegistrationFit:
    """An estimated registration and how each GPS position fits it.

    Attributes:
        residuals_m: (N,) distance between each registered camera centre and its GPS position.
        inliers: (N,) bool, the positions the final least-squares fit used.
    """

    registration: GeoRegistration
    residuals_m: FloatArray
    inliers: BoolArray

    @property
    def rms_m(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_m[self.inliers] ** 2)))


def estimate_registration(
    centers: FloatArray, gps: FloatArray, max_error_m: float = DEFAULT_MAX_ERROR_M, seed: int = 0
) -> RegistrationFit:
    """The registration mapping camera centres onto their GPS positions: pycolmap's
    LO-RANSAC similarity (``estimate_sim3d_robust``), then a least-squares similarity
    (``estimate_sim3d``) over the positions within ``max_error_m`` of it.

    Args:
        centers: (N, 3) camera centres in the map frame.
        gps: (N, 3) their GPS positions [latitude°, longitude°, height m].
        max_error_m: RANSAC inlier threshold in metres (about 3× the GPS accuracy).

    Raises:
        InvalidInputError: fewer than three positions, the centres on a line, no similarity
            found, or one whose orientation the positions fix worse than
            ``MAX_ROTATION_SIGMA_DEG``.
    """
    centers = np.asarray(centers, np.float64)
    gps = np.asarray(gps, np.float64)
    if len(centers) < MIN_GPS_REFERENCES:
        raise InvalidInputError(
            f"estimating a geo-registration needs at least {MIN_GPS_REFERENCES} references "
            f"with a GPS position; the map has {len(centers)}"
        )
    spread = np.linalg.svd(centers - centers.mean(axis=0), compute_uv=False)
    if spread[0] <= 0 or spread[1] < COLLINEAR_RATIO * spread[0]:
        raise InvalidInputError(
            "the references with a GPS position lie on a line: the rotation about it is "
            "unobservable; add references off that line or set the registration by hand"
        )
    origin = Geodetic(*np.mean(gps, axis=0))
    enu = enu_from_geodetic(gps, origin)
    options = pycolmap.RANSACOptions(max_error=max_error_m, random_seed=seed)
    # a dict (tgt_from_src, num_inliers, inlier_mask) at run time, whatever the stubs say
    robust: Any = pycolmap.estimate_sim3d_robust(centers, enu, options)
    if robust is None:
        raise InvalidInputError("no similarity maps the camera centres onto their GPS positions")
    inliers: BoolArray = np.asarray(robust["inlier_mask"], np.bool_)
    if inliers.sum() < MIN_GPS_REFERENCES:
        raise InvalidInputError(
            f"fewer than {MIN_GPS_REFERENCES} GPS positions agree within {max_error_m} m"
        )
    refined: Any = pycolmap.estimate_sim3d(centers[inliers], enu[inliers])
    refined = refined or robust["tgt_from_src"]
    residuals = _residuals(refined, centers, enu)
    rms = float(np.sqrt(np.mean(residuals[inliers] ** 2)))
    count = int(inliers.sum())
    # a least-squares fit over n points: σ of the centroid ≈ rms/√n; of the rotation ≈ rms over
    # the layout's radius of gyration about its weakest axis, /√n
    radius = float(np.sqrt(spread[1] ** 2 / len(centers))) * float(refined.scale)
    rotation_sigma_deg = float(np.degrees(rms / max(radius, 1e-9) / np.sqrt(count)))
    if rotation_sigma_deg > MAX_ROTATION_SIGMA_DEG:
        raise InvalidInputError(
            f"the references with a GPS position span about {2 * radius:.1f} m across their "
            f"narrowest direction against a GPS scatter of {rms:.1f} m (rms, {count} "
            f"positions): the registration's orientation would be uncertain by about "
            f"{min(rotation_sigma_deg, 180.0):.0f}° (more than {MAX_ROTATION_SIGMA_DEG:g}°); "
            "add GPS positions of references farther apart, or set the registration by hand"
        )
    registration = GeoRegistration(
        origin,
        np.asarray(refined.rotation.matrix(), np.float64),
        np.asarray(refined.translation, np.float64),
        float(refined.scale),
        position_sigma_m=rms / np.sqrt(count),
        rotation_sigma_deg=rotation_sigma_deg,
    )
    return RegistrationFit(registration, residuals, inliers)


def _residuals(sim: Any, centers: FloatArray, enu: FloatArray) -> FloatArray:
    """(N,) distances in metres between the mapped centres and their ENU GPS positions."""
    matrix = np.asarray(sim.matrix(), np.float64)
    mapped = centers @ matrix[:, :3].T + matrix[:, 3]
    return np.asarray(np.linalg.norm(mapped - enu, axis=1), np.float64)
