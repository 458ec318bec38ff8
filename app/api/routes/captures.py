"""Capture sessions of a map: create, upload frames, submit, read, delete."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, Form, Response, UploadFile

from app.api.deps import (
    AdminKey,
    AdmissionDep,
    BlobsDep,
    CaptureRunnerDep,
    Limit,
    LocalizersDep,
    Offset,
    SessionsDep,
    SettingsDep,
    json_form_schema,
    parse_json_form,
    read_upload,
)
from app.errors import problem_responses
from app.schemas.captures import (
    CaptureFrameMetadata,
    CaptureFrameOut,
    CaptureSessionCreate,
    CaptureSessionOut,
    CaptureSessionPage,
)
from app.usecases import captures

router = APIRouter(prefix="/v1/maps/{map_id}/sessions", tags=["capture sessions"])

FRAME_HELP = (
    'JSON string (schema CaptureFrameMetadata): {"name": str, "camera": {"model": "PINHOLE", '
    '"width": int, "height": int, "params": [fx, fy, cx, cy]}, and the pose in the session: '
    '"session_pose": {"matrix": 4×4} (ARKit / ARCore, OpenGL axes) or "cam_from_session": '
    '{"rotation": [qw, qx, qy, qz], "translation": [tx, ty, tz]} (COLMAP), and optionally '
    '"gps": {"latitude", "longitude", "height"?, "accuracy_m"?} (default: the image\'s EXIF '
    "GPS)}"
)


@router.post(
    "",
    status_code=201,
    operation_id="create_capture_session",
    dependencies=[AdminKey],
    responses=problem_responses(400, 401, 403, 404, 409, 413, 422),
)
def create_session(
    map_id: str, body: CaptureSessionCreate, sessions: SessionsDep, response: Response
) -> CaptureSessionOut:
    """Opens a capture session of the map: upload its frames in capture order
    (``POST …/frames``), then submit it (``POST …/submit``). The service localizes a spread
    of its frames against the map, estimates ``map_from_session`` and, when the alignment is
    well determined, adds every frame as a reference with its pose mapped into the map; a
    session that cannot be aligned is refused with its reason and adds nothing. On an empty
    map the session defines the map's frame."""
    row = captures.create_session(sessions, map_id, body.name, body.metric, body.keep_all)
    response.headers["Location"] = f"/v1/maps/{map_id}/sessions/{row.id}"
    return CaptureSessionOut.from_row(row)


@router.get(
    "",
    operation_id="list_capture_sessions",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404, 422),
)
def list_sessions(
    map_id: str, sessions: SessionsDep, offset: Offset = 0, limit: Limit = 20
) -> CaptureSessionPage:
    rows, total = captures.list_sessions(sessions, map_id, offset, limit)
    items = [CaptureSessionOut.from_row(row) for row in rows]
    return CaptureSessionPage(items=items, total=total, offset=offset, limit=limit)


@router.get(
    "/{session_id}",
    operation_id="get_capture_session",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404),
)
def get_session(map_id: str, session_id: str, sessions: SessionsDep) -> CaptureSessionOut:
    """The session's state, progress and, once decided, its alignment: ``map_from_session``,
    the checked frames' residuals and the reason of a refusal."""
    return CaptureSessionOut.from_row(captures.get_session(sessions, map_id, session_id))


@router.post(
    "/{session_id}/frames",
    status_code=201,
    operation_id="add_capture_frame",
    dependencies=[AdminKey],
    responses=problem_responses(400, 401, 403, 404, 409, 413, 422, 503),
)
def add_frame(
    map_id: str,
    session_id: str,
    admission: AdmissionDep,
    sessions: SessionsDep,
    localizers: LocalizersDep,
    settings: SettingsDep,
    blobs: BlobsDep,
    image: Annotated[UploadFile, File(description="JPEG or PNG")],
    metadata: Annotated[
        str,
        Form(description=FRAME_HELP, json_schema_extra=json_form_schema(CaptureFrameMetadata)),
    ],
    depth: Annotated[
        UploadFile | None,
        File(description="Optional depth: 16-bit PNG in millimetres or .npy float32 metres"),
    ] = None,
) -> CaptureFrameOut:
    """Uploads the next frame of an open session (409 once it is submitted, or when it holds
    ``SLLOC_MAX_SESSION_FRAMES`` frames). The image is decoded and checked against its
    camera now; its bytes wait in the blob store until the session is added or refused."""
    meta = parse_json_form(CaptureFrameMetadata, metadata, "metadata")
    with admission.admit():
        image_bytes = read_upload(image, settings.max_upload_bytes, "image")
        depth_bytes = read_upload(depth, settings.max_upload_bytes, "depth") if depth else None
        row = captures.add_frame(
            sessions,
            localizers,
            blobs,
            map_id,
            session_id,
            meta.to_new_frame(),
            image_bytes,
            depth_bytes,
            settings.max_session_frames,
        )
    return CaptureFrameOut.from_row(row)


@router.post(
    "/{session_id}/submit",
    status_code=202,
    operation_id="submit_capture_session",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404, 409, 422),
)
def submit_session(
    map_id: str, session_id: str, sessions: SessionsDep, runner: CaptureRunnerDep
) -> CaptureSessionOut:
    """Closes the session and queues its alignment in the background; poll the session for
    its progress and decision (``added`` or ``refused``)."""
    return CaptureSessionOut.from_row(captures.submit_session(sessions, map_id, session_id, runner))


@router.delete(
    "/{session_id}",
    status_code=204,
    operation_id="delete_capture_session",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404, 409),
)
def delete_session(
    map_id: str, session_id: str, sessions: SessionsDep, blobs: BlobsDep
) -> Response:
    """Deletes the session with its frames not added (an alignment in progress stops); the
    references an added session made stay. 409 while its frames are being added."""
    captures.delete_session(sessions, blobs, map_id, session_id)
    return Response(status_code=204)
