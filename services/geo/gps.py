"""GPS fixes: what a reference or a query may carry, and the one read from a JPEG's EXIF."""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from PIL import ExifTags

from services.errors import InvalidInputError
from services.geo.geodesy import HEIGHT_RANGE_M, Geodetic
from services.imaging.exif import header_exif

# EXIF GPS tags (EXIF 2.32, GPS IFD)
_LAT_REF, _LAT, _LON_REF, _LON, _ALT_REF, _ALT = 1, 2, 3, 4, 5, 6
_H_POSITIONING_ERROR = 31
# a GPS accuracy beyond the Earth's circumference says nothing
MAX_GPS_ACCURACY_M = 4e7


@dataclass(frozen=True)
class GpsFix:
    """A WGS84 position: degrees; ``height`` in metres (None: unknown); ``accuracy_m`` the
    horizontal 1-σ in metres (None: unknown)."""

    latitude: float
    longitude: float
    height: float | None = None
    accuracy_m: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.latitude) and -90.0 <= self.latitude <= 90.0):
            raise InvalidInputError("gps.latitude must be within [-90, 90] degrees")
        if not (math.isfinite(self.longitude) and -180.0 <= self.longitude <= 180.0):
            raise InvalidInputError("gps.longitude must be within [-180, 180] degrees")
        if self.height is not None:
            low, high = HEIGHT_RANGE_M
            if not (math.isfinite(self.height) and low <= self.height <= high):
                raise InvalidInputError(
                    f"gps.height must be within {low:g}…{high:g} m (a physical height)"
                )
        if self.accuracy_m is not None and not (
            math.isfinite(self.accuracy_m) and 0 < self.accuracy_m <= MAX_GPS_ACCURACY_M
        ):
            raise InvalidInputError(
                f"gps.accuracy_m must be a positive number of at most {MAX_GPS_ACCURACY_M:g} m"
            )

    def geodetic(self) -> Geodetic:
        """The fix as a geodetic point, an unknown height taken as 0."""
        return Geodetic(self.latitude, self.longitude, self.height or 0.0)


def gps_from_exif(image_bytes: bytes) -> GpsFix | None:
    """The GPS position in the image's EXIF (JPEG, PNG eXIf), or None when it has none or an
    unreadable one. EXIF altitude is above sea level; it is taken as the height unchanged (the
    geoid's offset from the ellipsoid is constant over a map and a registration absorbs it).
    Only the header is read (``header_exif``): the pixel limit is the caller's to enforce."""
    try:
        gps = header_exif(image_bytes).get_ifd(ExifTags.IFD.GPSInfo)
    except (OSError, SyntaxError, ValueError, EOFError, struct.error):
        return None
    try:
        latitude = _degrees(gps[_LAT], gps.get(_LAT_REF, "N"), "S")
        longitude = _degrees(gps[_LON], gps.get(_LON_REF, "E"), "W")
        height = None
        if _ALT in gps:
            height = float(gps[_ALT]) * (-1.0 if _below_sea_level(gps.get(_ALT_REF)) else 1.0)
        accuracy = float(gps[_H_POSITIONING_ERROR]) if _H_POSITIONING_ERROR in gps else None
        return GpsFix(latitude, longitude, height, accuracy or None)
    except (KeyError, TypeError, ValueError, ZeroDivisionError, InvalidInputError):
        return None


def _degrees(dms: object, ref: object, negative: str) -> float:
    degrees, minutes, seconds = (float(v) for v in dms)  # type: ignore[attr-defined]
    sign = -1.0 if str(ref).strip().upper().startswith(negative) else 1.0
    return sign * (degrees + minutes / 60.0 + seconds / 3600.0)


def _below_sea_level(ref: object) -> bool:
    if isinstance(ref, bytes):
        return ref[:1] == b"\x01"
    return ref == 1
