"""Localize a query image against a map."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, Form, UploadFile

from app.api.deps import (
    AdmissionDep,
    ClientKey,
    LocalizeContextDep,
    MetricsDep,
    QueryGrowthDep,
    QueryOutcomesDep,
    SessionsDep,
    SettingsDep,
    json_form_schema,
    parse_json_form,
    read_upload,
    read_uploads,
)
from app.errors import problem_responses
from app.schemas.localize import LocalizeParamsIn, LocalizeResult
from app.usecases import geo
from app.usecases.localize import localize as localize_image
from app.usecases.localize_frames import localize_with_session
from services.errors import InvalidInputError
from services.estimators.registry import DEFAULT_ESTIMATOR

router = APIRouter(prefix="/v1/maps/{map_id}", tags=["localize"])

PARAMS_HELP = (
    "JSON string (schema LocalizeParamsIn), all keys optional: "
    f'{{"camera": {{...}}, "estimator": "{DEFAULT_ESTIMATOR}", "top_k": 10, '
    '"prior": {"position": [x, y, z], "radius": m}, "return_inliers": false, "max_error_px": 12}'
)


@router.post(
    "/localize",
    operation_id="localize",
    dependencies=[ClientKey],
    responses=problem_responses(400, 401, 404, 409, 413, 422, 503),
)
def localize(
    map_id: str,
    sessions: SessionsDep,
    context: LocalizeContextDep,
    settings: SettingsDep,
    admission: AdmissionDep,
    image: Annotated[
        list[UploadFile],
        File(
            description="Query image, JPEG or PNG; repeat the part for several frames (each "
            "described by params.frames, in order; together within the upload limit)"
        ),
    ],
    metrics: MetricsDep,
    growth: QueryGrowthDep,
    outcomes: QueryOutcomesDep,
    params: Annotated[
        str, Form(description=PARAMS_HELP, json_schema_extra=json_form_schema(LocalizeParamsIn))
    ] = "{}",
    depth: Annotated[
        UploadFile | None,
        File(description="Optional query depth: 16-bit PNG in millimetres or .npy float32 m"),
    ] = None,
) -> LocalizeResult:
    """Returns 200 with ``localized: false`` and a ``reason`` when the image cannot be
    localized (``time_budget_exceeded`` past the time budget); 4xx only for bad input; 409
    ``feature-models-missing`` when none of the map's references is described as this
    server describes queries (their models are not built here; the detail names them); 503
    with ``Retry-After`` when every worker is busy and the queue is full."""
    body = parse_json_form(LocalizeParamsIn, params, "params")
    frames = body.to_frames()
    if frames is None and len(image) > 1:
        raise InvalidInputError(
            f"{len(image)} image parts: several frames need params.frames (one session pose "
            "per image)"
        )
    # admitted before the uploads are read: only admitted requests hold them in memory
    with admission.admit():
        images = read_uploads(image, settings.max_upload_bytes, "image")
        depth_bytes = read_upload(depth, settings.max_upload_bytes, "depth") if depth else None
        request, registration = geo.with_gps_hint(
            sessions, map_id, body.to_request(), body.gps.to_fix() if body.gps else None
        )
        if frames is not None:
            session_result = localize_with_session(
                context,
                map_id,
                request,
                frames,
                images,
                depth_bytes,
                max_frames=settings.max_frames,
            )
        else:
            result = localize_image(context, map_id, request, images[0], depth_bytes)
    if frames is not None:
        joint = session_result.result
        metrics.observe_localization(joint)
        return LocalizeResult.from_session_result(
            session_result,
            body.return_inliers,
            geo.geopose_answer(registration, session_result.result),
            body.output,
        )
    metrics.observe_localization(result)
    growth.offer(map_id, images[0], request.camera, result)
    outcomes.record(result)
    return LocalizeResult.from_result(
        result, body.return_inliers, geo.geopose_answer(registration, result), body.output
    )
