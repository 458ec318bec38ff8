"""Reference images of a map: add (multipart upload), list, get, delete."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, Form, Query, Request, Response, UploadFile
from starlette.concurrency import run_in_threadpool

from app.api.deps import (
    AdminKey,
    ClientKey,
    LocalizerDep,
    SessionsDep,
    SettingsDep,
    parse_json_form,
    read_upload,
)
from app.errors import not_found, problem_responses
from app.operations import add_reference_image, image_out
from app.schemas.images import ImageMetadata, ImageOut, ImagePage
from db.repositories.images import ImageRepository
from db.repositories.maps import MapRepository

router = APIRouter(prefix="/v1/maps/{map_id}/images", tags=["images"])

METADATA_HELP = (
    'JSON string: {"name": str, "camera": {"model": "PINHOLE", "width": int, "height": int, '
    '"params": [fx, fy, cx, cy]}, "cam_from_world": {"rotation": [qw, qx, qy, qz], '
    '"translation": [tx, ty, tz]}}'
)


@router.post(
    "",
    status_code=201,
    operation_id="add_image",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404, 409, 413, 422),
)
async def add_image(
    request: Request,
    map_id: str,
    sessions: SessionsDep,
    localizer: LocalizerDep,
    settings: SettingsDep,
    image: Annotated[UploadFile, File(description="JPEG or PNG")],
    metadata: Annotated[str, Form(description=METADATA_HELP)],
    depth: Annotated[
        UploadFile | None,
        File(description="Optional depth: 16-bit PNG in millimetres or .npy float32 metres"),
    ] = None,
) -> ImageOut:
    meta = parse_json_form(ImageMetadata, metadata, "metadata")
    image_bytes = read_upload(image, settings.max_upload_bytes, "image")
    depth_bytes = read_upload(depth, settings.max_upload_bytes, "depth") if depth else None
    trainer = request.app.state.vocabulary_trainer if settings.global_model is None else None
    return await run_in_threadpool(
        add_reference_image, sessions, localizer, map_id, meta, image_bytes, depth_bytes, trainer
    )


@router.get(
    "",
    operation_id="list_images",
    dependencies=[ClientKey],
    responses=problem_responses(401, 404, 422),
)
def list_images(
    map_id: str,
    sessions: SessionsDep,
    offset: int = Query(0, ge=0),
    limit: int = Query(100, ge=1, le=1000),
) -> ImagePage:
    with sessions() as session:
        if MapRepository(session).get(map_id) is None:
            raise not_found("map", map_id)
        rows, total = ImageRepository(session).page(map_id, offset, limit)
        items = [image_out(row) for row in rows]
    return ImagePage(items=items, total=total, offset=offset, limit=limit)


@router.get(
    "/{image_id}",
    operation_id="get_image",
    dependencies=[ClientKey],
    responses=problem_responses(401, 404),
)
def get_image(map_id: str, image_id: str, sessions: SessionsDep) -> ImageOut:
    with sessions() as session:
        row = ImageRepository(session).get(map_id, image_id)
        if row is None:
            if MapRepository(session).get(map_id) is None:
                raise not_found("map", map_id)
            raise not_found("image", image_id)
        return image_out(row)


@router.delete(
    "/{image_id}",
    status_code=204,
    operation_id="delete_image",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404),
)
def delete_image(map_id: str, image_id: str, sessions: SessionsDep) -> Response:
    with sessions.begin() as session:
        if not ImageRepository(session).delete(map_id, image_id):
            if MapRepository(session).get(map_id) is None:
                raise not_found("map", map_id)
            raise not_found("image", image_id)
    return Response(status_code=204)
