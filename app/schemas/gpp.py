"""The Open AR Cloud GeoPose Protocol (OSCP GPP) request and response, versions 1 and 2, as
the published clients send them: field names as the protocol spells them.

Version 1 carries ``sensorReadings`` as a list of ``{sensorId, timestamp, privacy, reading}``
whose kind is the type of the sensor of that id in ``sensors`` (camera intrinsics may sit in
the sensor's ``params``); version 2 carries an object of per-kind lists (``cameraReadings``,
``geolocationReadings``, …). Only what a visual positioning answer uses is read: the first
camera reading, the first geolocation reading and the last prior pose; other readings and
fields (privacy, wifi, accelerometer…) are accepted and ignored. ``GeoPoseReq.to_query`` reads
either shape into the use case's ``GppQuery``."""

from __future__ import annotations

import math
from typing import Any, TypeVar

from pydantic import AliasChoices, BaseModel, ConfigDict, Field, ValidationError, field_validator
from pydantic.alias_generators import to_camel

from app.schemas.geo import GeoPoseSchema
from app.usecases.gpp import GppAccuracy, GppIntrinsics, GppQuery, GppReading
from services.errors import InvalidInputError
from services.geo.gps import GpsFix

# timestamps: milliseconds since the Unix epoch, or (gpp-access before 0.1) an ISO string
Timestamp = float | str | None


class _Lenient(BaseModel):
    """Fields in the protocol's camelCase; fields slloc does not use (privacy, timestamps,
    other sensors' readings…) are ignored."""

    model_config = ConfigDict(extra="ignore", alias_generator=to_camel, populate_by_name=True)


class CameraParam(_Lenient):
    model: str | None = Field(
        None, description="COLMAP model name (UNKNOWN_CAMERA, UNKNOWN or absent: no intrinsics)"
    )
    model_params: list[float] | None = Field(None, description="COLMAP parameter order")

    def to_intrinsics(self) -> GppIntrinsics:
        params = None if self.model_params is None else tuple(self.model_params)
        return GppIntrinsics(self.model, params)


class ImageOrientation(_Lenient):
    """Only the upright, unmirrored image (rotation a multiple of 360°, mirrored false) is
    served; other values are answered 422 rather than localized wrongly."""

    mirrored: bool = False
    rotation: float = Field(0.0, allow_inf_nan=False, description="degrees")


class CameraReading(_Lenient):
    sensor_id: str | int | None = None
    sequence_number: int | None = None
    image_format: str | None = Field(
        None,
        description="JPG, JPEG or PNG (encoded bytes), or RGBA32, RGB24, GRAY8 (raw pixels "
        "of ``size``). JPEG and PNG bytes are recognised by their signature whatever the "
        "label says",
    )
    size: list[int] | None = Field(
        None,
        min_length=2,
        max_length=2,
        description="width, height; optional for JPEG and PNG (read from the image)",
    )
    image_bytes: str = Field(description="base64")
    image_orientation: ImageOrientation | None = None
    params: CameraParam | None = None

    def to_reading(self) -> GppReading:
        orientation = self.image_orientation or ImageOrientation()
        return GppReading(
            self.image_bytes,
            self.image_format,
            None if self.size is None else (self.size[0], self.size[1]),
            orientation.mirrored,
            orientation.rotation,
        )


def _finite_or_none(value: object) -> object:
    """NaN / ±inf (Python clients' json.dumps writes them) read as absent."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


class GeolocationReading(_Lenient):
    sensor_id: str | int | None = None
    latitude: float = Field(ge=-90, le=90, allow_inf_nan=False)
    longitude: float = Field(ge=-180, le=180, allow_inf_nan=False)
    altitude: float | None = Field(None, allow_inf_nan=False)
    accuracy: float | None = Field(
        None,
        ge=0,
        allow_inf_nan=False,
        description="horizontal 1-σ in metres; 0 or absent: unknown",
    )

    _finite = field_validator("altitude", "accuracy", mode="before")(_finite_or_none)


class SensorReadings(_Lenient):
    """Version 2's readings. ``geoLocationReadings`` (as @oarc/gpp-access spells it) is read
    like ``geolocationReadings``."""

    camera_readings: list[CameraReading] = Field(
        min_length=1, max_length=16, description="the first one is localized"
    )
    geolocation_readings: list[GeolocationReading] | None = Field(
        None,
        max_length=64,
        validation_alias=AliasChoices(
            "geolocationReadings", "geoLocationReadings", "geolocation_readings"
        ),
        description="the first one narrows retrieval (also read as geoLocationReadings)",
    )


class SensorReadingV1(_Lenient):
    """Version 1's reading: its kind is that of the sensor ``sensorId`` in ``sensors`` (or,
    without one, what its fields are: ``imageBytes`` a camera, ``latitude`` a geolocation)."""

    sensor_id: str | int | None = None
    timestamp: Timestamp = None
    reading: dict[str, Any] | None = None


class Sensor(_Lenient):
    id: str | int | None = None
    type: str | None = Field(None, description="camera, geolocation, wifi, …")
    params: CameraParam | None = Field(
        None, description="a camera's intrinsics (version 1 puts them here)"
    )


class GeoPoseAccuracy(BaseModel):
    position: float = Field(description="metres: the mean of the three axes' 1-σ")
    orientation: float = Field(description="degrees: the mean of the three angles' 1-σ")

    @classmethod
    def from_accuracy(cls, accuracy: GppAccuracy) -> GeoPoseAccuracy:
        return cls(position=accuracy.position_m, orientation=accuracy.orientation_deg)


class PriorPosition(_Lenient):
    lat: float = Field(ge=-90, le=90, allow_inf_nan=False)
    lon: float = Field(ge=-180, le=180, allow_inf_nan=False)
    h: float | None = Field(None, allow_inf_nan=False)


class PriorGeoPose(_Lenient):
    position: PriorPosition


class PriorAccuracy(_Lenient):
    position: float | None = Field(None, ge=0, allow_inf_nan=False)

    _finite = field_validator("position", mode="before")(_finite_or_none)


class PriorPose(_Lenient):
    """A GeoPose answer received before (``GeoPoseResp``): its position narrows retrieval
    like a GPS fix of its position accuracy. Entries without a ``geopose`` are ignored."""

    timestamp: Timestamp = None
    accuracy: PriorAccuracy | None = None
    geopose: PriorGeoPose | None = None


class GeoPoseReq(_Lenient):
    id: str = Field(max_length=255)
    timestamp: Timestamp = None
    type: str = "geopose"
    sensors: list[Sensor] = Field(default_factory=list, max_length=64)
    sensor_readings: SensorReadings | list[SensorReadingV1] = Field(
        description="version 2: an object of per-kind lists; version 1: a list of "
        "{sensorId, reading}"
    )
    prior_poses: list[PriorPose] | None = Field(
        None,
        max_length=64,
        description="earlier answers: the last one with a geopose narrows retrieval (before "
        "the GPS fix)",
    )

    def to_query(self) -> GppQuery:
        """The camera reading, position hint and protocol version of either request shape.

        Raises:
            InvalidInputError: no camera reading, or a version 1 reading that is not one.
        """
        sensors = {str(s.id): s for s in self.sensors if s.id is not None}
        if isinstance(self.sensor_readings, SensorReadings):
            cameras = self.sensor_readings.camera_readings
            fixes = self.sensor_readings.geolocation_readings or []
            version = 2
        else:
            cameras, fixes = [], []
            for i, item in enumerate(self.sensor_readings):
                sensor = sensors.get(str(item.sensor_id))
                kind = (sensor.type or "").lower() if sensor is not None else ""
                data = item.reading or {}
                if kind == "camera" or (not kind and "imageBytes" in data):
                    cameras.append(_v1_reading(CameraReading, data, i, item.sensor_id))
                elif kind == "geolocation" or (not kind and "latitude" in data):
                    fixes.append(_v1_reading(GeolocationReading, data, i, item.sensor_id))
            if not cameras:
                raise InvalidInputError(
                    "sensorReadings: no camera reading (a sensor of type camera)"
                )
            version = 1
        reading = cameras[0]
        params = reading.params
        if params is None and reading.sensor_id is not None:
            sensor = sensors.get(str(reading.sensor_id))
            params = sensor.params if sensor is not None else None
        return GppQuery(
            reading.to_reading(),
            None if params is None else params.to_intrinsics(),
            self._hint(fixes),
            version,
        )

    def _hint(self, fixes: list[GeolocationReading]) -> GpsFix | None:
        """The last prior pose with a position, else the first GPS fix (accuracy 0:
        unknown)."""
        for prior in reversed(self.prior_poses or []):
            if prior.geopose is not None:
                p = prior.geopose.position
                accuracy = prior.accuracy.position if prior.accuracy is not None else None
                return GpsFix(p.lat, p.lon, p.h, accuracy or None)
        if fixes:
            fix = fixes[0]
            return GpsFix(fix.latitude, fix.longitude, fix.altitude, fix.accuracy or None)
        return None


T = TypeVar("T", CameraReading, GeolocationReading)


def _v1_reading(
    model: type[T], data: dict[str, object], index: int, sensor_id: str | int | None
) -> T:
    """Version 1's ``reading`` object validated as ``model``, with the reading's sensor id.

    Raises:
        InvalidInputError: the first of its validation errors, located in the request.
    """
    try:
        reading = model.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise InvalidInputError(
            f"sensorReadings[{index}].reading.{where}: {first['msg']}"
        ) from None
    if reading.sensor_id is None:
        reading = reading.model_copy(update={"sensor_id": sensor_id})
    return reading


class GeoPoseResp(BaseModel):
    id: str
    timestamp: float = Field(description="milliseconds since the Unix epoch")
    accuracy: GeoPoseAccuracy
    type: str = "geopose"
    geopose: GeoPoseSchema
