"""WGS84 geodesy through pycolmap's ``GPSTransform``: geodetic (latitude, longitude, height
above the ellipsoid) ↔ ECEF ↔ a local East-North-Up (ENU) frame. No ellipsoid maths here."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
import pycolmap

from services.types import FloatArray

# heights above the WGS84 ellipsoid that a camera, a GPS fix or a registration's origin may
# have, metres: from below the deepest ocean trench (about −11,000 m) to the edge of space
HEIGHT_RANGE_M = (-12_000.0, 100_000.0)


@cache
def _gps() -> Any:
    return pycolmap.GPSTransform(pycolmap.GPSTransformEllipsoid.WGS84)


@dataclass(frozen=True)
class Geodetic:
    """A WGS84 point: latitude and longitude in degrees, height in metres above the ellipsoid."""

    latitude: float
    longitude: float
    height: float = 0.0

    def array(self) -> FloatArray:
        return np.array([self.latitude, self.longitude, self.height], np.float64)


def ecef_from_geodetic(lat_lon_h: FloatArray) -> FloatArray:
    """(N, 3) [latitude°, longitude°, height m] → (N, 3) ECEF metres."""
    return np.asarray(_gps().ellipsoid_to_ecef(np.atleast_2d(lat_lon_h)), np.float64)


def geodetic_from_ecef(ecef: FloatArray) -> FloatArray:
    """(N, 3) ECEF metres → (N, 3) [latitude°, longitude°, height m]."""
    return np.asarray(_gps().ecef_to_ellipsoid(np.atleast_2d(ecef)), np.float64)


def enu_from_geodetic(lat_lon_h: FloatArray, origin: Geodetic) -> FloatArray:
    """(N, 3) geodetic points → (N, 3) metres in the ENU frame at ``origin``."""
    return np.asarray(
        _gps().ellipsoid_to_enu(
            np.atleast_2d(lat_lon_h), origin.latitude, origin.longitude, origin.height
        ),
        np.float64,
    )


def geodetic_from_enu(enu: FloatArray, origin: Geodetic) -> FloatArray:
    """(N, 3) metres in the ENU frame at ``origin`` → (N, 3) geodetic points."""
    return np.asarray(
        _gps().enu_to_ellipsoid(
            np.atleast_2d(enu), origin.latitude, origin.longitude, origin.height
        ),
        np.float64,
    )


def ecef_from_enu_rotation(origin: Geodetic) -> FloatArray:
    """(3, 3) rotation taking ENU directions at ``origin`` to ECEF directions: its columns are
    East, North and Up in ECEF (the ENU map is affine, so differences of mapped points are
    exact)."""
    ecef = np.asarray(
        _gps().enu_to_ecef(
            np.vstack([np.zeros(3), np.eye(3)]), origin.latitude, origin.longitude, origin.height
        ),
        np.float64,
    )
    return np.asarray((ecef[1:] - ecef[0]).T, np.float64)
