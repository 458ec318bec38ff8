"""Positions on the globe as they cross the API: GPS fixes, a map's geo-registration and the
OGC GeoPose (Basic-Quaternion) of a localized camera."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, Field

from db.geo import StoredRegistration
from services.geo.geodesy import HEIGHT_RANGE_M, Geodetic
from services.geo.geopose import GeoPose, GeoPoseAccuracy
from services.geo.gps import MAX_GPS_ACCURACY_M, GpsFix
from services.geo.registration import (
    DEFAULT_MAX_ERROR_M,
    MAX_ENU_TRANSLATION_M,
    SCALE_RANGE,
    GeoRegistration,
)

# numbers as JSON numbers: a boolean is not one (lax mode would read false as 0)
Number = Annotated[float, Field(strict=True, allow_inf_nan=False)]
Latitude = Field(ge=-90, le=90, allow_inf_nan=False, description="WGS84 degrees")
Longitude = Field(ge=-180, le=180, allow_inf_nan=False, description="WGS84 degrees")
# metres above the WGS84 ellipsoid, within the physical range
Height = Annotated[Number, Field(ge=HEIGHT_RANGE_M[0], le=HEIGHT_RANGE_M[1])]
EnuMetres = Annotated[Number, Field(ge=-MAX_ENU_TRANSLATION_M, le=MAX_ENU_TRANSLATION_M)]


class GpsSchema(BaseModel):
    """A GPS position (WGS84). ``height`` in metres above the ellipsoid (EXIF altitudes, above
    sea level, are taken as they are); ``accuracy_m`` the horizontal 1-σ in metres."""

    latitude: Number = Latitude
    longitude: Number = Longitude
    height: Height | None = None
    accuracy_m: Number | None = Field(None, gt=0, le=MAX_GPS_ACCURACY_M)

    def to_fix(self) -> GpsFix:
        return GpsFix(self.latitude, self.longitude, self.height, self.accuracy_m)

    @classmethod
    def from_fix(cls, fix: GpsFix) -> GpsSchema:
        return cls(
            latitude=fix.latitude,
            longitude=fix.longitude,
            height=fix.height,
            accuracy_m=fix.accuracy_m,
        )


class GeodeticSchema(BaseModel):
    latitude: Number = Latitude
    longitude: Number = Longitude
    height: Height = Field(0.0, description="metres above the WGS84 ellipsoid")


class EnuFromMapSchema(BaseModel):
    rotation: list[Number] = Field(
        [1.0, 0.0, 0.0, 0.0],
        min_length=4,
        max_length=4,
        description="enu_from_map rotation quaternion [w, x, y, z]",
    )
    translation: list[EnuMetres] = Field(
        [0.0, 0.0, 0.0],
        min_length=3,
        max_length=3,
        description=f"metres in ENU; |translation| at most {MAX_ENU_TRANSLATION_M:g}",
    )


class GeoRegistrationIn(BaseModel):
    """A registration set by hand: ``x_enu = scale · R · x_map + t``, with ENU (x East,
    y North, z Up, metres) anchored at ``origin``. A map whose frame is already metric with
    z up and x East has the identity rotation and scale 1."""

    origin: GeodeticSchema
    enu_from_map: EnuFromMapSchema = EnuFromMapSchema()
    scale: Number = Field(
        1.0, ge=SCALE_RANGE[0], le=SCALE_RANGE[1], description="metres per map unit"
    )

    def to_registration(self) -> GeoRegistration:
        o = self.origin
        return GeoRegistration.from_quaternion(
            Geodetic(o.latitude, o.longitude, o.height),
            np.array(self.enu_from_map.rotation, np.float64),
            np.array(self.enu_from_map.translation, np.float64),
            self.scale,
        )


class GeoRegistrationEstimateIn(BaseModel):
    max_error_m: Number = Field(
        DEFAULT_MAX_ERROR_M,
        gt=0,
        le=10_000,
        description="RANSAC inlier threshold in metres between a registered camera centre and "
        "its GPS position (about 3 × the GPS accuracy)",
    )


class ResidualOut(BaseModel):
    image_id: str
    name: str
    residual_m: float
    inlier: bool


class GeoRegistrationOut(BaseModel):
    origin: GeodeticSchema
    enu_from_map: EnuFromMapSchema
    scale: float
    source: Literal["manual", "estimated"]
    position_sigma_m: float = Field(description="1-σ of a registered position (0 when manual)")
    rotation_sigma_deg: float = Field(description="1-σ of a registered orientation")
    num_references: int | None = Field(None, description="references with GPS (estimated)")
    num_inliers: int | None = None
    residual_rms_m: float | None = None
    residuals: list[ResidualOut] | None = Field(
        None, description="per reference, in the answer of an estimate"
    )

    @classmethod
    def from_stored(
        cls, stored: StoredRegistration, residuals: list[ResidualOut] | None = None
    ) -> GeoRegistrationOut:
        r = stored.registration
        return cls(
            origin=GeodeticSchema(
                latitude=r.origin.latitude, longitude=r.origin.longitude, height=r.origin.height
            ),
            enu_from_map=EnuFromMapSchema(
                rotation=[float(v) for v in r.quaternion],
                translation=[float(v) for v in r.translation],
            ),
            scale=r.scale,
            source="estimated" if stored.source == "estimated" else "manual",
            position_sigma_m=r.position_sigma_m,
            rotation_sigma_deg=r.rotation_sigma_deg,
            num_references=stored.num_references,
            num_inliers=stored.num_inliers,
            residual_rms_m=stored.residual_rms_m,
            residuals=residuals,
        )


class GeoPositionSchema(BaseModel):
    lat: float
    lon: float
    h: float


class QuaternionXyzwSchema(BaseModel):
    x: float
    y: float
    z: float
    w: float


class GeoPoseSchema(BaseModel):
    """OGC GeoPose Basic-Quaternion: ``quaternion`` rotates the camera frame (OpenGL axes:
    x right, y up, z backward) into East-North-Up at ``position``."""

    position: GeoPositionSchema
    quaternion: QuaternionXyzwSchema

    @classmethod
    def from_geopose(cls, pose: GeoPose) -> GeoPoseSchema:
        x, y, z, w = (float(v) for v in pose.quaternion_xyzw)
        p = pose.position
        return cls(
            position=GeoPositionSchema(lat=p.latitude, lon=p.longitude, h=p.height),
            quaternion=QuaternionXyzwSchema(x=x, y=y, z=z, w=w),
        )


class GeoPoseAccuracySchema(BaseModel):
    """1-σ: horizontal and vertical position in metres, yaw (heading) in degrees."""

    horizontal_m: float
    vertical_m: float
    yaw_deg: float

    @classmethod
    def from_accuracy(cls, accuracy: GeoPoseAccuracy) -> GeoPoseAccuracySchema:
        return cls(
            horizontal_m=accuracy.horizontal_m,
            vertical_m=accuracy.vertical_m,
            yaw_deg=accuracy.yaw_deg,
        )
