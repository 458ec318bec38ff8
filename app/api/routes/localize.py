"""Localize a query image against a map."""

from __future__ import annotations

import threading
from dataclasses import replace
from typing import Annotated

import numpy as np
from fastapi import APIRouter, File, Form, Request, UploadFile
from starlette.concurrency import run_in_threadpool

from app.api.deps import (
    ClientKey,
    LocalizerDep,
    SessionsDep,
    SettingsDep,
    parse_json_form,
    read_upload,
)
from app.errors import invalid, not_found, problem_responses
from app.schemas.geometry import PoseSchema
from app.schemas.localize import (
    InliersOut,
    LocalizeParamsIn,
    LocalizeResult,
    RetrievedOut,
    Timings,
)
from db.repositories.maps import MapRepository
from db.store import SqlReferenceStore
from services.estimators.options import EstimatorOptions
from services.pipeline import LocalizationResult, LocalizeParams
from services.retrieval.search import PositionPrior

router = APIRouter(prefix="/v1/maps/{map_id}", tags=["localize"])

PARAMS_HELP = (
    'JSON string, all keys optional: {"camera": {...}, "estimator": "e5p1", "top_k": 10, '
    '"prior": {"position": [x, y, z], "radius": m}, "return_inliers": false, "max_error_px": 12}'
)


def _to_params(body: LocalizeParamsIn, default_estimator: str, max_top_k: int) -> LocalizeParams:
    if body.top_k > max_top_k:
        raise invalid(f"top_k may be at most {max_top_k}")
    options = EstimatorOptions()
    if body.max_error_px is not None:
        options = replace(options, ransac=replace(options.ransac, max_error_px=body.max_error_px))
    return LocalizeParams(
        camera=body.camera.to_camera() if body.camera else None,
        estimator=body.estimator or default_estimator,
        top_k=body.top_k,
        prior=PositionPrior(np.array(body.prior.position), body.prior.radius)
        if body.prior
        else None,
        options=options,
    )


def _to_result(result: LocalizationResult, return_inliers: bool) -> LocalizeResult:
    pose = result.cam_from_world
    return LocalizeResult(
        localized=result.localized,
        reason=result.reason,
        estimator=result.estimator,
        cam_from_world=PoseSchema.from_rigid(pose) if pose is not None else None,
        camera_center=[float(v) for v in pose.center] if pose is not None else None,
        num_inliers=result.num_inliers,
        confidence=result.confidence,
        retrieved=[
            RetrievedOut(
                image_id=r.image_id,
                name=r.name,
                score=r.score,
                num_matches=r.num_matches,
                num_inliers=r.num_inliers,
            )
            for r in result.retrieved
        ],
        inliers=[
            InliersOut(
                image_id=r.image_id,
                query_xy=r.query_xy.tolist(),
                reference_xy=r.reference_xy.tolist(),
            )
            for r in result.retrieved
            if r.num_inliers > 0
        ]
        if return_inliers
        else None,
        timings_ms=Timings(**{k: round(v, 3) for k, v in result.timings_ms.items()}),
    )


@router.post(
    "/localize",
    operation_id="localize",
    dependencies=[ClientKey],
    responses=problem_responses(401, 404, 413, 422),
)
async def localize(
    map_id: str,
    request: Request,
    sessions: SessionsDep,
    localizer: LocalizerDep,
    settings: SettingsDep,
    image: Annotated[UploadFile, File(description="Query image, JPEG or PNG")],
    params: Annotated[str, Form(description=PARAMS_HELP)] = "{}",
    depth: Annotated[
        UploadFile | None,
        File(description="Optional query depth: 16-bit PNG in millimetres or .npy float32 m"),
    ] = None,
) -> LocalizeResult:
    """Returns 200 with ``localized: false`` and a ``reason`` when the image cannot be
    localized; 4xx only for bad input."""
    body = parse_json_form(LocalizeParamsIn, params, "params")
    with sessions() as session:
        map_row = MapRepository(session).get(map_id)
        if map_row is None:
            raise not_found("map", map_id)
        default_estimator = map_row.default_estimator
        localizer = localizer.for_map(map_row.max_keypoints, map_row.max_side)
    engine_params = _to_params(body, default_estimator, settings.max_top_k)
    image_bytes = read_upload(image, settings.max_upload_bytes, "image")
    depth_bytes = read_upload(depth, settings.max_upload_bytes, "depth") if depth else None
    store = SqlReferenceStore(
        sessions,
        map_id,
        localizer.extractor.name,
        localizer.global_descriptor.name,
        request.app.state.retrieval_cache,
        vlad=settings.global_model is None,
        trainer=request.app.state.vocabulary_trainer,
    )
    slots: threading.BoundedSemaphore = request.app.state.localize_slots

    def run() -> LocalizationResult:
        with slots:
            return localizer.localize(image_bytes, engine_params, store, depth_bytes)

    result = await run_in_threadpool(run)
    return _to_result(result, body.return_inliers)
