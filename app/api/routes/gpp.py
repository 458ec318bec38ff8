"""The Open AR Cloud GeoPose Protocol (OSCP GPP v1): existing GPP clients localize against a
geo-registered map unchanged."""

from __future__ import annotations

import time
from dataclasses import replace

from fastapi import APIRouter

from app.api.deps import (
    AdmissionDep,
    ClientKey,
    LocalizeContextDep,
    MetricsDep,
    SessionsDep,
    SettingsDep,
)
from app.errors import ProblemError, problem_responses
from app.schemas.geo import GeoPoseSchema
from app.schemas.gpp import GeoPoseAccuracy, GeoPoseReq, GeoPoseResp
from app.usecases import geo, gpp
from app.usecases.localize import localize as localize_image

router = APIRouter(prefix="/v1/maps/{map_id}", tags=["geo"])


@router.post(
    "/geopose",
    operation_id="gpp_geopose",
    dependencies=[ClientKey],
    responses=problem_responses(400, 401, 404, 413, 422, 503),
)
def geopose(
    map_id: str,
    body: GeoPoseReq,
    sessions: SessionsDep,
    context: LocalizeContextDep,
    settings: SettingsDep,
    admission: AdmissionDep,
    metrics: MetricsDep,
) -> GeoPoseResp:
    """A GeoPose Protocol request (``GeoPoseReq``: the first camera reading's image and
    intrinsics, the first geolocation reading as a retrieval hint) answered with a
    ``GeoPoseResp``: the camera's OGC GeoPose (OpenGL camera axes in East-North-Up) and its
    mean position (m) and orientation (°) accuracy. The map must be geo-registered (else 422);
    an image that cannot be localized is 404 ``not-localized`` with the reason, since the
    protocol's answer has no way to say it."""
    reading = body.sensor_readings.camera_readings[0]
    request, gps = gpp.localize_request(body)
    registration = geo.map_registration(sessions, map_id)
    if registration is None:
        raise ProblemError(
            422,
            "not-geo-registered",
            "Map not geo-registered",
            "a GeoPose needs the map's geo-registration: PUT or POST "
            f"/v1/maps/{map_id}/geo-registration…",
        )
    if gps is not None:
        request = replace(request, prior=geo.gps_prior(registration, gps))
    with admission.admit():  # before the image is decoded from base64: bounded copies
        image_bytes = gpp.image_bytes(reading, settings.max_image_pixels)
        result = localize_image(context, map_id, request, image_bytes)
    metrics.observe_localization(result.estimator, result.reason, result.timings_ms)
    answer = geo.geopose_answer(registration, result)
    if answer is None:
        raise ProblemError(
            404, "not-localized", "Not localized", f"the image was not localized: {result.reason}"
        )
    pose, accuracy = answer
    return GeoPoseResp(
        id=body.id,
        timestamp=time.time() * 1000.0,
        accuracy=GeoPoseAccuracy(
            position=(accuracy.horizontal_m + accuracy.vertical_m) / 2, orientation=accuracy.yaw_deg
        ),
        geopose=GeoPoseSchema.from_geopose(pose),
    )
