"""The Open AR Cloud GeoPose Protocol (OSCP GPP v1 and v2): existing GPP clients localize
against a geo-registered map unchanged."""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Annotated

from fastapi import APIRouter, Header, Query
from fastapi.responses import JSONResponse, Response

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
from services.geo.geopose import GeoPose

router = APIRouter(prefix="/v1/maps/{map_id}", tags=["geo"])


@router.post(
    "/geopose",
    operation_id="gpp_geopose",
    dependencies=[ClientKey],
    response_model=GeoPoseResp,
    responses={
        200: {"content": {gpp.OSCP_MEDIA_TYPE: {}}},
        **problem_responses(400, 401, 404, 406, 409, 413, 422, 503),
    },
)
def geopose(
    map_id: str,
    body: GeoPoseReq,
    sessions: SessionsDep,
    context: LocalizeContextDep,
    settings: SettingsDep,
    admission: AdmissionDep,
    metrics: MetricsDep,
    accept: Annotated[
        str | None,
        Header(
            description="`application/vnd.oscp+json; version=1.0` or `2.0` answers in that "
            "protocol version under that media type; JSON or `*/*` (or none) in the "
            "request's own version; anything else is 406"
        ),
    ] = None,
    camera_axes: Annotated[
        gpp.CameraAxes,
        Query(
            description="Camera axes the answer's quaternion rotates into East-North-Up: "
            "forward_left_up (x forward, y left, z up, as OpenVPS answers and sparcl reads; "
            "identity = level, looking East) or opengl (x right, y up, z backward, as "
            "/localize's geopose; identity = looking down, image top North)"
        ),
    ] = "forward_left_up",
) -> Response:
    """A GeoPose Protocol request, version 1 (``sensorReadings`` a list of
    ``{sensorId, reading}``) or 2 (``sensorReadings.cameraReadings`` …), answered with a
    ``GeoPoseResp``: the camera's OGC GeoPose in East-North-Up (camera axes per
    ``camera_axes``) and the means of its position (m) and orientation (°) 1-σ over the three
    components. The first camera reading is localized (JPEG/PNG recognised by their bytes,
    whatever ``imageFormat`` says; ``size`` optional for them); the last prior pose, else the
    first geolocation reading, narrows retrieval to references near it. The map must be
    geo-registered (else 422); an image that cannot be localized is 404 ``not-localized`` with
    the reason, since the protocol's answer has no way to say it."""
    query = body.to_query()
    negotiated = gpp.answer_version(accept, query.version)
    if negotiated is None:
        raise ProblemError(
            406,
            "not-acceptable",
            "Not acceptable",
            f"Accept {accept!r}: served are {gpp.OSCP_MEDIA_TYPE}; version=1.0 or 2.0, and "
            "application/json",
        )
    gpp.check_orientation(query.reading)
    registration = geo.map_registration(sessions, map_id)
    if registration is None:
        raise ProblemError(
            422,
            "not-geo-registered",
            "Map not geo-registered",
            "a GeoPose needs the map's geo-registration: PUT or POST "
            f"/v1/maps/{map_id}/geo-registration…",
        )
    with admission.admit():  # before the image is decoded from base64: bounded copies
        image_bytes, size = gpp.image_bytes(query.reading, settings.max_image_pixels)
        request = gpp.localize_request(query, size)
        if query.hint is not None:
            request = replace(request, prior=geo.gps_prior(registration, query.hint))
        result = localize_image(context, map_id, request, image_bytes)
    metrics.observe_localization(result)
    answer = geo.geopose_answer(registration, result)
    if answer is None:
        raise ProblemError(
            404, "not-localized", "Not localized", f"the image was not localized: {result.reason}"
        )
    pose, accuracy = answer
    pose = GeoPose(pose.position, gpp.answer_rotation(pose, camera_axes))
    response = GeoPoseResp(
        id=body.id,
        timestamp=time.time() * 1000.0,
        accuracy=GeoPoseAccuracy.from_accuracy(gpp.answer_accuracy(accuracy)),
        geopose=GeoPoseSchema.from_geopose(pose),
    )
    return JSONResponse(response.model_dump(mode="json"), media_type=negotiated[1])
