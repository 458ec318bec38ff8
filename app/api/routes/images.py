"""Reference images of a map: add (multipart upload), list, get, delete."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, Form, Query, Response, UploadFile

from app.api.deps import (
    AdminKey,
    AdmissionDep,
    BlobsDep,
    ClientKey,
    EngineConfigDep,
    EvaluatorDep,
    Limit,
    LocalizersDep,
    Offset,
    ReferenceCacheDep,
    SessionsDep,
    SettingsDep,
    TrainerDep,
    json_form_schema,
    parse_json_form,
    read_upload,
)
from app.errors import problem_responses
from app.schemas.images import ImageMetadata, ImageOut, ImagePage
from app.usecases import images

router = APIRouter(prefix="/v1/maps/{map_id}/images", tags=["images"])

METADATA_HELP = (
    'JSON string (schema ImageMetadata): {"name": str, "camera": {"model": "PINHOLE", '
    '"width": int, "height": int, "params": [fx, fy, cx, cy]}, "cam_from_world": '
    '{"rotation": [qw, qx, qy, qz], "translation": [tx, ty, tz]}}'
)


@router.post(
    "",
    status_code=201,
    operation_id="add_image",
    dependencies=[AdminKey],
    responses=problem_responses(400, 401, 403, 404, 409, 413, 422, 503),
)
def add_image(
    map_id: str,
    admission: AdmissionDep,
    sessions: SessionsDep,
    localizers: LocalizersDep,
    settings: SettingsDep,
    engine: EngineConfigDep,
    trainer: TrainerDep,
    blobs: BlobsDep,
    evaluator: EvaluatorDep,
    image: Annotated[UploadFile, File(description="JPEG or PNG")],
    metadata: Annotated[
        str, Form(description=METADATA_HELP, json_schema_extra=json_form_schema(ImageMetadata))
    ],
    depth: Annotated[
        UploadFile | None,
        File(description="Optional depth: 16-bit PNG in millimetres or .npy float32 metres"),
    ] = None,
) -> ImageOut:
    """The image's bytes as sent (and the depth's) are kept in the blob store
    (``SLLOC_BLOB_URL``) beside its features: ``GET …/images/{image_id}/original``. 503
    ``blob-store-unavailable`` (nothing stored) while the blob store cannot be reached or
    refuses writes."""
    meta = parse_json_form(ImageMetadata, metadata, "metadata")
    # admitted before the uploads are read: only admitted requests hold them in memory
    with admission.admit():
        image_bytes = read_upload(image, settings.max_upload_bytes, "image")
        depth_bytes = read_upload(depth, settings.max_upload_bytes, "depth") if depth else None
        stored = images.add_reference_image(
            sessions,
            localizers,
            map_id,
            meta.to_new_image(),
            image_bytes,
            depth_bytes,
            trainer=trainer if engine.vlad else None,
            slots=admission.slots,
            preview_max_side=settings.preview_max_side,
            blobs=blobs,
        )
    evaluator.evaluate_if_due(map_id)
    return ImageOut.from_stored(stored)


@router.get(
    "",
    operation_id="list_images",
    dependencies=[ClientKey],
    responses=problem_responses(401, 404, 422),
)
def list_images(
    map_id: str,
    sessions: SessionsDep,
    offset: Offset = 0,
    limit: Limit = 100,
    stale: Annotated[
        bool | None,
        Query(
            description="true: only the images flagged stale (a capture session's frames "
            "that cover them no longer match them); false: only the others"
        ),
    ] = None,
) -> ImagePage:
    stored, total = images.list_images(sessions, map_id, offset, limit, stale)
    items = [ImageOut.from_stored(image) for image in stored]
    return ImagePage(items=items, total=total, offset=offset, limit=limit)


@router.get(
    "/{image_id}",
    operation_id="get_image",
    dependencies=[ClientKey],
    responses=problem_responses(401, 404),
)
def get_image(map_id: str, image_id: str, sessions: SessionsDep) -> ImageOut:
    return ImageOut.from_stored(images.get_image(sessions, map_id, image_id))


@router.get(
    "/{image_id}/preview",
    operation_id="get_image_preview",
    dependencies=[ClientKey],
    response_class=Response,
    responses={
        200: {"content": {"image/jpeg": {}}, "description": "The JPEG preview"},
        **problem_responses(401, 404),
    },
)
def get_image_preview(map_id: str, image_id: str, sessions: SessionsDep) -> Response:
    """A JPEG of the reference image for display, its longer side at most
    ``SLLOC_PREVIEW_MAX_SIDE`` pixels: scale the image's pixel coordinates (inliers) by the
    preview's width over ``camera.width``. 404 for an image stored without a preview (added
    with previews off)."""
    preview = images.get_preview(sessions, map_id, image_id)
    # an image id names one image for good (images are never modified in place)
    headers = {"Cache-Control": "private, max-age=86400, immutable"}
    return Response(preview.jpeg, media_type="image/jpeg", headers=headers)


@router.get(
    "/{image_id}/original",
    operation_id="get_image_original",
    dependencies=[ClientKey],
    response_class=Response,
    responses={
        200: {
            "content": {"image/jpeg": {}, "image/png": {}},
            "description": "The image's bytes as uploaded",
        },
        **problem_responses(401, 404, 503),
    },
)
def get_image_original(
    map_id: str, image_id: str, sessions: SessionsDep, blobs: BlobsDep
) -> Response:
    """The reference image's bytes exactly as they were uploaded; the ``ETag`` is their
    SHA-256 (``original_sha256`` of the image). 404 for an image added before originals
    were kept (``has_original`` false) or whose original is missing from the blob store;
    503 ``blob-store-unavailable`` while the blob store cannot be reached."""
    original = images.get_original(sessions, blobs, map_id, image_id)
    headers = {
        "Cache-Control": "private, max-age=86400, immutable",
        "ETag": f'"{original.sha256}"',
    }
    return Response(original.data, media_type=original.media_type, headers=headers)


@router.delete(
    "/{image_id}",
    status_code=204,
    operation_id="delete_image",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404),
)
def delete_image(
    map_id: str,
    image_id: str,
    sessions: SessionsDep,
    features_cache: ReferenceCacheDep,
    blobs: BlobsDep,
    evaluator: EvaluatorDep,
) -> Response:
    """Deletes the image's row and features, then its originals in the blob store."""
    images.delete_image(sessions, map_id, image_id, features_cache, blobs)
    evaluator.evaluate_if_due(map_id)
    return Response(status_code=204)
