"""``slloc session``: push a capture session (posed frames in the device's own frame) to a
running server and print its decision, or show a session's decision again.

    slloc session push CSV --url URL --map MAP [--name NAME] [--unknown-scale] \
        [--frames "range:500-749"] [--api-key KEY]
    slloc session show --url URL --map MAP SESSION

The CSV is an import CSV (``slloc import --csv``); its pose columns are taken as each frame's
``cam_from_session`` (COLMAP convention), its GPS columns as the frame's fix, frames in row
order. The client functions
(``create_session`` … ``push_session``, ``wait_decided``) serve the benchmarks too
(``tools/benchmarks/capture_sessions.py``). httpx is imported only where a request is made,
so that ``slloc`` builds its parser without the evaluation tools.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d

if TYPE_CHECKING:
    import httpx

    from tools.evaluation.datasets import Dataset, PosedImage

# states in which a session is decided: nothing changes any more
DECIDED = ("added", "refused", "failed")
# how often frame uploads are reported on stderr
PROGRESS_EVERY = 25
# retries of a request the server refused for now (503, admission), honouring Retry-After
BUSY_RETRIES = 30


class SessionApiError(RuntimeError):
    """A request failed: a transport error, or an error status with its problem detail."""


@dataclass(frozen=True)
class SessionFrame:
    """One frame to upload: its name in the session, its image (bytes, or a file read when
    uploaded), its camera, its ``cam_from_session`` (COLMAP axes: x right, y down), an
    optional depth (16-bit PNG in millimetres or .npy float32 metres) and GPS fix."""

    name: str
    image: bytes | Path
    camera: Camera
    cam_from_session: Rigid3d
    depth: bytes | Path | None = None
    # the device's GPS fix as the API takes it ({latitude, longitude, height?, accuracy_m?})
    gps: dict[str, float] | None = None


Progress = Callable[[str], None]


def _log(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _problem(response: httpx.Response) -> str:
    """The problem+json ``detail`` (with its field errors) or the start of the body."""
    try:
        body = response.json()
    except ValueError:
        return response.text[:300]
    if not isinstance(body, dict):
        return response.text[:300]
    detail = str(body.get("detail") or body.get("title") or response.text[:300])
    errors = body.get("errors")
    if isinstance(errors, list) and errors:
        detail += ": " + "; ".join(
            f"{'.'.join(str(p) for p in e.get('loc', []))}: {e.get('msg')}"
            if isinstance(e, dict)
            else str(e)
            for e in errors
        )
    return detail


def request(http: httpx.Client, method: str, url: str, **kwargs: Any) -> httpx.Response:
    """The response of a successful request; a 503 (the server is busy) is retried after its
    ``Retry-After`` up to ``BUSY_RETRIES`` times.

    Raises:
        SessionApiError: a transport error or another error status.
    """
    import httpx

    for _ in range(BUSY_RETRIES + 1):
        try:
            response = http.request(method, url, **kwargs)
        except httpx.HTTPError as exc:
            raise SessionApiError(f"{method} {url}: {exc}") from exc
        if response.status_code != 503:
            break
        time.sleep(float(response.headers.get("Retry-After", "1")))
    if response.is_error:
        raise SessionApiError(f"{method} {url}: {response.status_code} {_problem(response)}")
    return response


def client(url: str, api_key: str | None = None, timeout_s: float = 600.0) -> httpx.Client:
    """An HTTP client of the server at ``url`` (``X-API-Key`` when a key is given)."""
    import httpx

    headers = {"X-API-Key": api_key} if api_key else {}
    return httpx.Client(base_url=url.rstrip("/"), headers=headers, timeout=timeout_s)


def resolve_map(http: httpx.Client, map_ref: str) -> str:
    """The id of the map whose id or name is ``map_ref``.

    Raises:
        SessionApiError: no such map, or the maps cannot be listed.
    """
    import httpx

    from tools.evaluation.self_evaluate import find_map_id

    try:
        return find_map_id(http, map_ref)
    except (ValueError, httpx.HTTPError) as exc:
        raise SessionApiError(str(exc)) from exc


def create_session(
    http: httpx.Client, map_id: str, name: str | None, metric: bool = True, keep_all: bool = False
) -> dict[str, Any]:
    """``POST /v1/maps/{map_id}/sessions``: the new session (``open``)."""
    body = {"name": name, "metric": metric, "keep_all": keep_all}
    answer: dict[str, Any] = request(http, "POST", f"/v1/maps/{map_id}/sessions", json=body).json()
    return answer


def _media_type(name: str, data: bytes) -> str:
    if data.startswith(b"\x89PNG"):
        return "image/png"
    if data.startswith(b"\x93NUMPY") or name.lower().endswith(".npy"):
        return "application/octet-stream"
    return "image/jpeg"


def _bytes(data: bytes | Path) -> bytes:
    return data.read_bytes() if isinstance(data, Path) else data


def frame_metadata(frame: SessionFrame) -> dict[str, Any]:
    """The ``metadata`` form field of a frame upload (``cam_from_session`` form)."""
    camera = frame.camera
    pose = frame.cam_from_session
    return {
        "name": frame.name,
        "camera": {
            "model": camera.model,
            "width": camera.width,
            "height": camera.height,
            "params": [float(p) for p in camera.params],
        },
        "cam_from_session": {
            "rotation": [float(v) for v in pose.quaternion],
            "translation": [float(v) for v in pose.translation],
        },
    } | ({"gps": frame.gps} if frame.gps is not None else {})


def upload_frame(
    http: httpx.Client, map_id: str, session_id: str, frame: SessionFrame
) -> dict[str, Any]:
    """``POST …/sessions/{session_id}/frames``: the stored frame."""
    image = _bytes(frame.image)
    image_name = frame.image.name if isinstance(frame.image, Path) else "frame"
    files = {"image": (image_name, image, _media_type(image_name, image))}
    if frame.depth is not None:
        depth = _bytes(frame.depth)
        depth_name = "depth.npy" if depth.startswith(b"\x93NUMPY") else "depth.png"
        files["depth"] = (depth_name, depth, _media_type(depth_name, depth))
    answer: dict[str, Any] = request(
        http,
        "POST",
        f"/v1/maps/{map_id}/sessions/{session_id}/frames",
        files=files,
        data={"metadata": json.dumps(frame_metadata(frame))},
    ).json()
    return answer


def submit_session(http: httpx.Client, map_id: str, session_id: str) -> dict[str, Any]:
    """``POST …/sessions/{session_id}/submit``: the session, now ``queued``."""
    answer: dict[str, Any] = request(
        http, "POST", f"/v1/maps/{map_id}/sessions/{session_id}/submit"
    ).json()
    return answer


def get_session(http: httpx.Client, map_id: str, session_id: str) -> dict[str, Any]:
    answer: dict[str, Any] = request(http, "GET", f"/v1/maps/{map_id}/sessions/{session_id}").json()
    return answer


def find_session(http: httpx.Client, map_id: str, session_ref: str) -> dict[str, Any]:
    """The session whose id or name is ``session_ref``.

    Raises:
        SessionApiError: no such session.
    """
    offset = 0
    while True:
        page = request(
            http,
            "GET",
            f"/v1/maps/{map_id}/sessions",
            params={"offset": offset, "limit": 1000},
        ).json()
        for item in page["items"]:
            if session_ref in (item["id"], item["name"]):
                return dict(item)
        offset += len(page["items"])
        if not page["items"] or offset >= page["total"]:
            raise SessionApiError(f"map {map_id} has no session named or with id {session_ref!r}")


def wait_decided(
    http: httpx.Client,
    map_id: str,
    session_id: str,
    poll_s: float = 1.0,
    timeout_s: float = 7200.0,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Polls the session every ``poll_s`` until it is decided (``DECIDED``); each change of
    state or progress goes to ``progress``.

    Raises:
        SessionApiError: a request failed, or the session is not decided in ``timeout_s``.
    """
    start = time.perf_counter()
    seen = None
    while True:
        session = get_session(http, map_id, session_id)
        done, total = session["progress"]["done"], session["progress"]["total"]
        now = (session["state"], done, total)
        if progress is not None and now != seen:
            progress(
                f"session {session['name']}: {session['state']} {done}/{total} "
                f"({time.perf_counter() - start:.0f} s)"
            )
        seen = now
        if session["state"] in DECIDED:
            return session
        if time.perf_counter() - start > timeout_s:
            raise SessionApiError(f"session {session_id} not decided after {timeout_s:.0f} s")
        time.sleep(poll_s)


def push_session(
    http: httpx.Client,
    map_id: str,
    name: str | None,
    frames: list[SessionFrame],
    metric: bool = True,
    progress: Progress | None = None,
    poll_s: float = 1.0,
    keep_all: bool = False,
) -> dict[str, Any]:
    """Creates a session on the map, uploads ``frames`` in order, submits it and returns it
    once decided, with ``upload_s`` (client seconds from creating to submitting) added.

    Raises:
        SessionApiError: a request failed (the session is left as it is).
    """
    start = time.perf_counter()
    session = create_session(http, map_id, name, metric, keep_all)
    session_id = session["id"]
    if progress is not None:
        progress(f"session {session['name']} ({session_id}) on map {map_id}: {len(frames)} frames")
    for done, frame in enumerate(frames, start=1):
        upload_frame(http, map_id, session_id, frame)
        if progress is not None and (done % PROGRESS_EVERY == 0 or done == len(frames)):
            progress(f"uploaded {done}/{len(frames)} ({time.perf_counter() - start:.0f} s)")
    submit_session(http, map_id, session_id)
    upload_s = time.perf_counter() - start
    decided = wait_decided(http, map_id, session_id, poll_s, progress=progress)
    return decided | {"upload_s": upload_s}


def job_seconds(session: dict[str, Any]) -> float | None:
    """Seconds from the job's start to its decision (None until both are known)."""
    started, finished = session.get("started_at"), session.get("finished_at")
    if not started or not finished:
        return None
    return (datetime.fromisoformat(finished) - datetime.fromisoformat(started)).total_seconds()


def _number(value: float | None, scale: float = 1.0, digits: int = 1) -> str:
    return "–" if value is None else f"{value * scale:.{digits}f}"


def summary(session: dict[str, Any]) -> str:
    """The session's decision as lines of text and a Markdown table of its checked frames."""
    lines = [
        f"session {session['name']} ({session['id']}) of map {session['map_id']}: "
        f"{session['state']}, {session['frames']} frames"
        + ("" if session["metric"] else " (unknown scale)")
    ]
    job_s = job_seconds(session)
    if job_s is not None:
        lines.append(f"job: {job_s:.1f} s")
    if session.get("error"):
        lines.append(f"error: {session['error']}")
    alignment = session.get("alignment")
    if alignment is None:
        if session["state"] not in DECIDED:
            done, total = session["progress"]["done"], session["progress"]["total"]
            lines.append(f"not decided yet ({done}/{total})")
        return "\n".join(lines)
    transform = alignment.get("map_from_session")
    if transform is not None:
        rotation = ", ".join(f"{v:.5f}" for v in transform["rotation"])
        translation = ", ".join(f"{v:.4f}" for v in transform["translation"])
        lines.append(
            f"map_from_session ({alignment['mode']}): rotation [{rotation}], "
            f"translation [{translation}], scale {transform['scale']:.4f}"
        )
    else:
        lines.append(f"map_from_session ({alignment['mode']}): none")
    path = f"path {alignment['path_length_m']:.2f} (session units)"
    if alignment["mode"] == "bootstrap":
        lines.append(f"{path}; the map was empty: the session defines its frame")
    else:
        lines.append(
            f"{path}, tolerance {_number(alignment.get('tolerance_m'), 100)} cm; agreeing "
            f"{alignment.get('agreeing')} of {alignment.get('confident')} confident, "
            f"{len(alignment['checked'])} checked"
        )
    if alignment.get("rms_position_m") is not None:
        lines.append(
            f"rms {_number(alignment['rms_position_m'], 100)} cm / "
            f"{_number(alignment['rms_rotation_deg'], digits=2)}°, standard error "
            f"{_number(alignment.get('position_stderr_m'), 100)} cm / "
            f"{_number(alignment.get('rotation_stderr_deg'), digits=2)}°"
        )
    if alignment.get("reason"):
        lines.append(f"reason: {alignment['reason']}")
    if alignment.get("drift_correction_m"):
        drift = alignment["drift_correction_m"]
        lines.append(
            f"drift corrected at the agreeing frames: median {_number(drift['median'], 100)} "
            f"cm, largest {_number(drift['max'], 100)} cm"
        )
    for stale in alignment.get("stale") or []:
        lines.append(f"flagged stale: {stale['name']} ({stale['image_id']}): {stale['reason']}")
    if alignment.get("added") is not None:
        skipped = alignment.get("skipped") or 0
        lines.append(
            f"added: {alignment['added']} frames"
            + (f" ({skipped} not added: their views were in the map)" if skipped else "")
        )
    if alignment["checked"]:
        lines += [
            "",
            "| frame | localized | confidence | position error cm | rotation error ° | agrees |",
            "|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {c['frame']} | {'yes' if c['localized'] else 'no'} | {c['confidence']:.2f} "
            f"| {_number(c['position_error_m'], 100)} "
            f"| {_number(c['rotation_error_deg'], digits=2)} | {'yes' if c['agrees'] else 'no'} |"
            for c in alignment["checked"]
        ]
    return "\n".join(lines)


def select_images(dataset: Dataset, rule: str | None) -> list[PosedImage]:
    """The images of ``dataset`` that a split rule selects (``tools/evaluation/split.py``,
    e.g. ``range:500-749 every:2``), in dataset order; None or ``all``: every image.

    Raises:
        ValueError: the rule is malformed or selects nothing.
    """
    from tools.evaluation.split import split_dataset

    if not rule or not rule.strip():
        return list(dataset.images)
    # the rule as a split's reference side (its query side takes everything and is unused)
    return split_dataset(dataset, rule, "all").references


def frames_from_csv(path: Path, rule: str | None = None) -> list[SessionFrame]:
    """The frames of an import CSV in row order, those ``rule`` selects (see
    ``select_images``; None: all); each row's ``cam_from_world`` is taken as the frame's
    ``cam_from_session``, its image name as the frame's name and its GPS columns
    (``latitude``, ``longitude``, ``gps_height``, ``gps_accuracy_m``) as its fix.

    Raises:
        OSError, ValueError: the CSV cannot be read, the rule is malformed or selects nothing.
    """
    from tools.evaluation.datasets import csv_dataset
    from tools.importers import read_csv

    gps = {
        item.metadata.name: item.metadata.gps.model_dump(exclude_none=True)
        for item in read_csv(path)
        if item.metadata.gps is not None
    }
    return [
        SessionFrame(
            image.name,
            image.image_path,
            image.camera,
            image.cam_from_world,
            image.depth_path,
            gps.get(image.name),
        )
        for image in select_images(csv_dataset(path), rule)
    ]


def add_session_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="session_command", required=True)
    push = sub.add_parser(
        "push",
        help="upload an import CSV's frames as a capture session of a map, submit it and "
        "print its decision (exit 1 unless added)",
    )
    push.add_argument(
        "csv",
        type=Path,
        help="import CSV; its pose columns are each frame's cam_from_session, in row order",
    )
    push.add_argument(
        "--frames",
        help='the rows to push, as a split rule: "range:500-749", "range:0-99 every:2", '
        '"list:FILE" (default: all)',
    )
    push.add_argument("--name", help="session name (default: the server's, session-<hex>)")
    push.add_argument(
        "--unknown-scale",
        action="store_true",
        help="the poses are not in metres: the server estimates the session's scale",
    )
    push.add_argument(
        "--keep-all",
        action="store_true",
        help="add every frame (default: only those that add a view at the map's spacing)",
    )
    show = sub.add_parser("show", help="print a session's state and decision")
    show.add_argument("session", help="session id or name")
    for command in (push, show):
        command.add_argument("--url", required=True, help="the server, e.g. http://127.0.0.1:8000")
        command.add_argument("--map", required=True, help="map name or id")
        command.add_argument("--api-key", help="an admin key (X-API-Key)")


def session_main(args: argparse.Namespace) -> int:
    """``slloc session push|show``: 0 when the session is added, 1 when refused or failed
    (``show``: also while undecided), 2 when a request or the CSV fails."""
    logging.getLogger("faiss.loader").setLevel(logging.WARNING)  # INFO lines on its import
    frames: list[SessionFrame] = []
    if args.session_command == "push":
        try:
            frames = frames_from_csv(args.csv, args.frames)
        except (OSError, ValueError) as exc:
            print(f"cannot read {args.csv}: {exc}", file=sys.stderr)
            return 2
    try:
        with client(args.url, args.api_key) as http:
            map_id = resolve_map(http, args.map)
            if args.session_command == "push":
                session = push_session(
                    http,
                    map_id,
                    args.name,
                    frames,
                    not args.unknown_scale,
                    progress=_log,
                    keep_all=args.keep_all,
                )
                _log(f"uploaded in {session['upload_s']:.1f} s")
            else:
                session = find_session(http, map_id, args.session)
    except SessionApiError as exc:
        print(f"slloc session {args.session_command}: {exc}", file=sys.stderr)
        return 2
    print(summary(session))
    return 0 if session["state"] == "added" else 1
