"""Capture sessions on real data: a server (``slloc serve``, its own SQLite database) builds a
map of a dataset's references with their ground-truth poses, localizes held-out queries, takes
a capture session whose poses are known only relative to its first frame and drift, and
localizes the queries again; the session's decision, its timings and the poses its frames were
added with (against the ground truth) are printed as Markdown tables and written to
``--out/results.json``.

    python -m tools.benchmarks.capture_sessions [--dataset redkitchen|kitti05 ...] \
        [--preset xfeat-lg] [--session-every 1] [--drift 0.01] [--yaw-drift 0.05] \
        [--seed 0] [--no-depth] [--quick] [--datasets-dir ../shared/datasets] \
        [--out out/capture-sessions]

Scenarios (dataset positions, split rules of ``tools/evaluation/split.py``):

- redkitchen: map = 0–499 every 5th, session = 500–749 (every ``--session-every``th),
  queries = 750–999 every 10th; kitti05: map = 0–149 every 3rd, session = 150–224,
  queries = 225–299 every 3rd.
- Negative sessions on the redkitchen map, before its session: (a) kitti05 frames 150–174
  (another place: expected refused); (b) the redkitchen session with its translations halved
  but declared metric (expected refused); (c) the same declared of unknown scale (expected
  added with a scale ≈ 2), on a second map built like the first so that it does not meet the
  frames of the redkitchen session (added to the first map after (b)).
- Stale references: a map of the dataset whose two references the session (redkitchen
  500–749, kitti05 120–224, which overlap their maps) covers best show frames of the other
  dataset, resized, poses kept; the stale flags of a self-evaluation of the map (its default
  sample, or ``--evaluation-sample``; the map's configuration), then those of the session,
  against them. ``--stale-only`` runs this scenario alone.
- Bootstrap: an empty map takes redkitchen 0–499 every 5th as a session (relative poses with
  drift), then localizes 500–999 every 10th against the ground truth expressed in the
  session's frame.

Session poses: ``cam_from_session = cam_from_world ∘ world_from_first`` (the first frame's
camera is the session's origin), drifted as a device's odometry would: a frame that travelled
``s`` metres from the first is moved by ``drift × s`` along a fixed horizontal direction
(seeded; horizontal = orthogonal to the first camera's y axis) and turned by
``yaw_drift × s`` degrees about that y axis (its orientation only; default 0.05°/m, well
under the 2° an agreeing frame may be off). The server's tolerance is max(5 cm, 1 % of the
path), so the default drift of 1 % puts the last frame at the edge of it.

``--quick``: 10 map frames, 10 session frames, 5 queries (a smoke run).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np

from app.schemas.geometry import CameraSchema
from services.geometry.rigid import Rigid3d, pose_error
from services.self_evaluation.summary import recall_key
from tools.evaluation.datasets import Dataset, PosedImage, open_dataset
from tools.evaluation.runner import HttpRunner
from tools.evaluation.server import LocalServer
from tools.session_push import (
    SessionApiError,
    SessionFrame,
    client,
    job_seconds,
    push_session,
    request,
    select_images,
)

DATASET_PATHS = {"redkitchen": "redkitchen", "kitti05": "kitti05/frames.csv"}
# query recall thresholds (metres, degrees)
QUERY_THRESHOLDS = ((0.05, 5.0), (0.25, 2.0))
# an added frame is "right" within these (metres, degrees)
ADDED_RIGHT = (0.03, 1.0)
PROGRESS_EVERY = 25


@dataclass(frozen=True)
class Scenario:
    """Split rules of one dataset: the map's references, the session, the queries."""

    map: str
    session: str
    queries: str


SCENARIOS = {
    "redkitchen": Scenario("range:0-499 every:5", "range:500-749", "range:750-999 every:10"),
    "kitti05": Scenario("range:0-149 every:3", "range:150-224", "range:225-299 every:3"),
}
QUICK_SCENARIOS = {
    "redkitchen": Scenario(
        "range:0-499 every:50", "range:500-749 every:25", "range:750-999 every:50"
    ),
    "kitti05": Scenario("range:0-149 every:15", "range:150-224 every:8", "range:225-299 every:15"),
}
# stale references: this many of the references the session covers best show another place;
# the session of each dataset that overlaps its map
STALE_SWAPS = 2
STALE_SESSIONS = {"redkitchen": "range:500-749", "kitti05": "range:120-224"}
# negative (a): frames of another place, pushed to the redkitchen map
OTHER_PLACE = ("kitti05", "range:150-174", "range:150-159")
# bootstrap: the session that starts an empty map, and the queries localized in it
BOOTSTRAP = Scenario("", "range:0-499 every:5", "range:500-999 every:10")
QUICK_BOOTSTRAP = Scenario("", "range:0-499 every:50", "range:500-999 every:100")


@dataclass(frozen=True)
class Options:
    preset: str
    session_every: int
    drift: float
    yaw_drift_deg_per_m: float
    seed: int
    depth: bool
    quick: bool
    datasets_dir: Path
    # a dataset's session rule instead of its scenario's (dataset name -> rule)
    sessions: dict[str, str] = field(default_factory=dict)
    # where the swapped references' images are written
    scratch: Path = Path("out/capture-sessions")
    # the stale-references scenario alone
    stale_only: bool = False
    # references its self-evaluation holds out (None: the server's default)
    evaluation_sample: int | None = None


def _log(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _y_rotation(angle_rad: float) -> Any:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def first_frame_truth(images: list[PosedImage], first: PosedImage) -> list[Rigid3d]:
    """Each image's ground truth in the frame of ``first``'s camera:
    ``cam_from_world ∘ world_from_first``."""
    world_from_first = first.cam_from_world.inverse()
    return [image.cam_from_world.compose(world_from_first) for image in images]


def drifted_session_poses(
    images: list[PosedImage],
    drift: float,
    yaw_drift_deg_per_m: float,
    seed: int,
    scale: float = 1.0,
) -> list[Rigid3d]:
    """``cam_from_session`` of each image (the first image's camera is the session's origin),
    drifted by ``drift`` × the distance travelled along a seeded horizontal direction and
    turned by ``yaw_drift_deg_per_m`` × that distance about the first camera's y axis;
    positions then multiplied by ``scale`` (a session of another unit)."""
    exact = first_frame_truth(images, images[0])
    centers = np.array([pose.center for pose in exact]).reshape(-1, 3)
    steps = np.linalg.norm(np.diff(centers, axis=0), axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(steps)])
    angle = np.random.default_rng(seed).uniform(0.0, 2.0 * np.pi)
    direction = np.array([np.cos(angle), 0.0, np.sin(angle)])  # ⊥ the first camera's y axis
    poses = []
    for pose, center, s in zip(exact, centers, travelled, strict=True):
        session_from_cam = _y_rotation(np.radians(yaw_drift_deg_per_m * s)) @ pose.rotation.T
        drifted = (center + drift * s * direction) * scale
        rotation = session_from_cam.T
        poses.append(Rigid3d(rotation, -rotation @ drifted))
    return poses


def session_frames(
    images: list[PosedImage], options: Options, scale: float = 1.0
) -> list[SessionFrame]:
    poses = drifted_session_poses(
        images, options.drift, options.yaw_drift_deg_per_m, options.seed, scale
    )
    return [
        SessionFrame(
            image.name,
            image.image_path,
            image.camera,
            pose,
            image.depth_path if options.depth else None,
        )
        for image, pose in zip(images, poses, strict=True)
    ]


def _finite(value: float) -> float | None:
    return value if np.isfinite(value) else None


def _percentile(values: list[float], q: float) -> float | None:
    """Nearest-rank percentile (``inf`` counts: a failure); None when there are no values or
    it is infinite."""
    if not values:
        return None
    ordered = sorted(values)
    rank = max(0, int(np.ceil(q / 100.0 * len(ordered))) - 1)
    return _finite(ordered[rank])


def localize_queries(
    runner: HttpRunner, queries: list[PosedImage], truth: list[Rigid3d]
) -> dict[str, Any]:
    """Localizes each query with its camera; recall at ``QUERY_THRESHOLDS`` and the median
    position error over all queries (a failure counts as infinitely far)."""
    records: list[dict[str, Any]] = []
    errors: list[tuple[float, float]] = []  # (metres, degrees); inf without a pose
    localized = 0
    start = time.perf_counter()
    for query, cam_from_world in zip(queries, truth, strict=True):
        params = {"camera": CameraSchema.from_camera(query.camera).model_dump()}
        outcome = runner.localize(query.image_path.read_bytes(), None, params)
        error = (float("inf"), float("inf"))
        if outcome.localized and outcome.cam_from_world is not None:
            error = pose_error(outcome.cam_from_world.to_rigid(), cam_from_world)
        localized += outcome.localized
        errors.append(error)
        records.append(
            {
                "query": query.name,
                "localized": outcome.localized,
                "reason": outcome.reason,
                "confidence": outcome.confidence,
                "position_error_m": _finite(error[0]),
                "rotation_error_deg": _finite(error[1]),
                "total_ms": outcome.timings_ms.get("total"),
                "wider_retrieval": bool(outcome.stats.get("wider_retrieval")),
                "retrieved": outcome.retrieved,
            }
        )
    recall = {
        recall_key(m, d): float(np.mean([p <= m and r <= d for p, r in errors]))
        for m, d in QUERY_THRESHOLDS
    }
    return {
        "queries": len(records),
        "localized": localized,
        "recall": recall,
        "median_position_m": _percentile([p for p, _ in errors], 50),
        "seconds": time.perf_counter() - start,
        "records": records,
    }


def build_map(url: str, name: str, images: list[PosedImage], options: Options) -> HttpRunner:
    """A map of ``images`` as references with their ground-truth poses (and depth), its
    retrieval vocabulary trained as an admin does after a bulk load, ready."""
    runner = HttpRunner(url, None, name, keep_map=True, features={"preset": options.preset})
    start = time.perf_counter()
    for done, image in enumerate(images, start=1):
        depth = image.depth_path.read_bytes() if options.depth and image.depth_path else None
        runner.add_reference(image, depth)
        if done % PROGRESS_EVERY == 0 or done == len(images):
            _log(
                f"map {name}: {done}/{len(images)} references ({time.perf_counter() - start:.0f} s)"
            )
    runner.index_references(len(images))
    return runner


def decision(session: dict[str, Any], expected: str) -> dict[str, Any]:
    """What the benchmark keeps of a decided session."""
    alignment = session.get("alignment") or {}
    transform = alignment.get("map_from_session")
    return {
        "id": session["id"],
        "name": session["name"],
        "expected": expected,
        "state": session["state"],
        "metric": session["metric"],
        "frames": session["frames"],
        "error": session.get("error"),
        "mode": alignment.get("mode"),
        "map_from_session": transform,
        "scale": transform["scale"] if transform else None,
        "reason": alignment.get("reason"),
        "path_length": alignment.get("path_length_m"),
        "tolerance_m": alignment.get("tolerance_m"),
        "confident": alignment.get("confident"),
        "agreeing": alignment.get("agreeing"),
        "checked": len(alignment.get("checked") or []),
        "rms_position_m": alignment.get("rms_position_m"),
        "rms_rotation_deg": alignment.get("rms_rotation_deg"),
        "position_stderr_m": alignment.get("position_stderr_m"),
        "rotation_stderr_deg": alignment.get("rotation_stderr_deg"),
        "added": alignment.get("added"),
        "upload_s": session.get("upload_s"),
        "job_s": job_seconds(session),
        "checked_frames": alignment.get("checked") or [],
        "stale": sorted(s["name"] for s in alignment.get("stale") or []),
    }


def run_session(
    http: httpx.Client,
    map_id: str,
    name: str,
    frames: list[SessionFrame],
    expected: str,
    metric: bool = True,
) -> dict[str, Any]:
    _log(f"session {name}: {len(frames)} frames, metric {metric}, expected {expected}")
    session = push_session(http, map_id, name, frames, metric, progress=_log)
    result = decision(session, expected)
    reason = f": {result['reason']}" if result["reason"] else ""
    _log(
        f"session {name}: {result['state']} (scale {result['scale']}, agreeing "
        f"{result['agreeing']}/{result['confident']}){reason}"
    )
    return result


def map_images(http: httpx.Client, map_id: str) -> dict[str, Rigid3d]:
    """Every reference of the map by name: its stored ``cam_from_world``."""
    poses: dict[str, Rigid3d] = {}
    offset = 0
    while True:
        page = request(
            http, "GET", f"/v1/maps/{map_id}/images", params={"offset": offset, "limit": 1000}
        ).json()
        for item in page["items"]:
            pose = item["cam_from_world"]
            poses[item["name"]] = Rigid3d.from_quaternion(
                np.array(pose["rotation"]), np.array(pose["translation"])
            )
        offset += len(page["items"])
        if not page["items"] or offset >= page["total"]:
            return poses


def added_pose_errors(
    http: httpx.Client,
    map_id: str,
    session_name: str,
    images: list[PosedImage],
    truth: list[Rigid3d],
) -> dict[str, Any]:
    """The poses the session's frames were added with against ``truth`` (in the map's
    frame): median, p90 and max of the position and rotation errors and the fraction within
    ``ADDED_RIGHT``."""
    stored = map_images(http, map_id)
    positions, rotations, missing = [], [], 0
    for image, cam_from_map in zip(images, truth, strict=True):
        pose = stored.get(f"{session_name}/{image.name}")
        if pose is None:
            missing += 1
            continue
        position_m, rotation_deg = pose_error(pose, cam_from_map)
        positions.append(position_m)
        rotations.append(rotation_deg)
    right_m, right_deg = ADDED_RIGHT
    return {
        "frames": len(images),
        "found": len(positions),
        "missing": missing,
        "position_m": {
            "median": _percentile(positions, 50),
            "p90": _percentile(positions, 90),
            "max": max(positions, default=None),
        },
        "rotation_deg": {
            "median": _percentile(rotations, 50),
            "p90": _percentile(rotations, 90),
            "max": max(rotations, default=None),
        },
        "within": float(
            np.mean(
                [p <= right_m and r <= right_deg for p, r in zip(positions, rotations, strict=True)]
            )
        )
        if positions
        else 0.0,
    }


def _open(options: Options, name: str) -> Dataset:
    return open_dataset(options.datasets_dir / DATASET_PATHS[name])


def measure(name: str, url: str, options: Options) -> dict[str, Any]:
    """Every scenario of one dataset on the server at ``url``."""
    dataset = _open(options, name)
    scenario = (QUICK_SCENARIOS if options.quick else SCENARIOS)[name]
    session_rule = options.sessions.get(name, scenario.session)
    if options.session_every > 1 and not options.quick:
        session_rule += f" every:{options.session_every}"
    references = select_images(dataset, scenario.map)
    session_images = select_images(dataset, session_rule)
    queries = select_images(dataset, scenario.queries)
    query_truth = [q.cam_from_world for q in queries]
    _log(
        f"{name}: map {len(references)} references ({scenario.map}), session "
        f"{len(session_images)} frames ({session_rule}), {len(queries)} queries "
        f"({scenario.queries})"
    )
    result: dict[str, Any] = {
        "dataset": name,
        "rules": {"map": scenario.map, "session": session_rule, "queries": scenario.queries},
    }
    with client(url) as http:
        if options.stale_only:
            result["stale"] = stale_scenario(http, url, name, options, options.scratch)
            return result
        start = time.perf_counter()
        runner = build_map(url, f"{name}-map", references, options)
        result["map"] = {
            "id": runner.map_id,
            "references": len(references),
            "features": runner.features,
            "seconds": time.perf_counter() - start,
        }
        result["queries_before"] = localize_queries(runner, queries, query_truth)
        sessions: dict[str, dict[str, Any]] = {}
        if name == "redkitchen":
            other_name, other_rule, other_quick = OTHER_PLACE
            other = select_images(
                _open(options, other_name), other_quick if options.quick else other_rule
            )
            sessions["other place (kitti05)"] = run_session(
                http, runner.map_id, "other-place", session_frames(other, options), "refused"
            )
            sessions["half scale, metric"] = run_session(
                http,
                runner.map_id,
                "half-scale-metric",
                session_frames(session_images, options, scale=0.5),
                "refused",
            )
        frames = session_frames(session_images, options)
        sessions["session"] = run_session(http, runner.map_id, "session", frames, "added")
        runner.wait_ready()
        added: dict[str, dict[str, Any]] = {}
        if sessions["session"]["state"] == "added":
            added["session"] = added_pose_errors(
                http,
                runner.map_id,
                "session",
                session_images,
                [i.cam_from_world for i in session_images],
            )
        result["queries_after"] = localize_queries(runner, queries, query_truth)
        if name == "redkitchen":
            second = build_map(url, f"{name}-map-2", references, options)
            key = "half scale, unknown scale"
            sessions[key] = run_session(
                http,
                second.map_id,
                "half-scale-unknown",
                session_frames(session_images, options, scale=0.5),
                "added",
                metric=False,
            )
            if sessions[key]["state"] == "added":
                added[key] = added_pose_errors(
                    http,
                    second.map_id,
                    "half-scale-unknown",
                    session_images,
                    [i.cam_from_world for i in session_images],
                )
            result["bootstrap"], added["bootstrap"] = bootstrap(http, url, dataset, options)
            sessions["bootstrap"] = result["bootstrap"].pop("session")
        result["sessions"] = sessions
        result["added"] = added
        result["stale"] = stale_scenario(http, url, name, options, options.scratch)
    return result


def swapped_references(
    references: list[PosedImage],
    session: list[PosedImage],
    others: list[PosedImage],
    folder: Path,
) -> list[PosedImage]:
    """``references`` with the ``STALE_SWAPS`` the session covers best (nearest to one of its
    frames, looking within 30° of it) showing images of ``others`` instead (resized to their
    cameras), poses and names kept."""
    centers = np.array([i.cam_from_world.center for i in session])
    axes = np.array([i.cam_from_world.rotation[2] for i in session])
    closeness = []
    for image in references:
        distance = np.linalg.norm(centers - image.cam_from_world.center, axis=1)
        facing = axes @ image.cam_from_world.rotation[2] >= np.cos(np.radians(30.0))
        closeness.append(float(distance[facing].min()) if facing.any() else np.inf)
    swap = set(np.argsort(closeness)[:STALE_SWAPS].tolist())
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for k, image in enumerate(references):
        if k not in swap:
            out.append(image)
            continue
        source = others[len(out) % len(others)].image_path
        other = cv2.imread(str(source), cv2.IMREAD_COLOR)
        if other is None:
            raise ValueError(f"{source}: not an image OpenCV reads")
        size = (image.camera.width, image.camera.height)
        path = folder / f"swapped-{k}.png"
        cv2.imwrite(str(path), cv2.resize(other, size, interpolation=cv2.INTER_AREA))
        out.append(replace(image, image_path=path, depth_path=None))
    return out


def stale_scenario(
    http: httpx.Client, url: str, name: str, options: Options, out: Path
) -> dict[str, Any]:
    """A map whose references the session covers best show another place: which references
    a self-evaluation of the map, then the session, flag stale, against those swapped."""
    dataset = _open(options, name)
    scenario = (QUICK_SCENARIOS if options.quick else SCENARIOS)[name]
    session_rule = STALE_SESSIONS[name] if not options.quick else scenario.session
    session_images = select_images(dataset, session_rule)
    other_name = "kitti05" if name == "redkitchen" else "redkitchen"
    others = select_images(_open(options, other_name), "range:0-99 every:10")
    references = swapped_references(
        select_images(dataset, scenario.map), session_images, others, out / f"{name}-swapped"
    )
    swapped = sorted(
        image.name for image in references if image.image_path.name.startswith("swapped-")
    )
    runner = build_map(url, f"{name}-stale", references, options)
    start = time.perf_counter()
    evaluation = request(
        http,
        "POST",
        f"/v1/maps/{runner.map_id}/evaluations",
        json={"configurations": [runner.features]}
        | ({"sample_size": options.evaluation_sample} if options.evaluation_sample else {}),
    ).json()
    location = f"/v1/maps/{runner.map_id}/evaluations/{evaluation['id']}"
    while evaluation["state"] in ("queued", "running"):
        time.sleep(1.0)
        evaluation = request(http, "GET", location).json()
    evaluated = sorted(s["name"] for s in (evaluation.get("result") or {}).get("stale", []))
    _log(
        f"{name}: self-evaluation {evaluation['state']} in {time.perf_counter() - start:.0f} s, "
        f"flagged {evaluated}"
    )
    session = run_session(
        http, runner.map_id, "stale", session_frames(session_images, options), "added"
    )
    flagged = session["stale"]
    return {
        "session_rule": session_rule,
        "state": session["state"],
        "swapped": swapped,
        "evaluation": {
            "state": evaluation["state"],
            "held_out": evaluation["progress"]["total"],
            "flagged": evaluated,
            "found": len(set(swapped) & set(evaluated)),
            "false_flags": len(set(evaluated) - set(swapped)),
        },
        "flagged": flagged,
        "found": len(set(swapped) & set(flagged)),
        "false_flags": len(set(flagged) - set(swapped)),
    }


def bootstrap(
    http: httpx.Client, url: str, dataset: Dataset, options: Options
) -> tuple[dict[str, Any], dict[str, Any]]:
    """An empty map started by a session; its queries against the ground truth in the
    session's frame. Returns (its figures with the session's decision under ``session``,
    the added poses' errors)."""
    scenario = QUICK_BOOTSTRAP if options.quick else BOOTSTRAP
    images = select_images(dataset, scenario.session)
    queries = select_images(dataset, scenario.queries)
    runner = HttpRunner(url, None, "bootstrap", keep_map=True, features={"preset": options.preset})
    session = run_session(
        http, runner.map_id, "bootstrap", session_frames(images, options), "added"
    )
    added: dict[str, Any] = {}
    figures: dict[str, Any] = {
        "rules": {"session": scenario.session, "queries": scenario.queries},
        "session": session,
    }
    if session["state"] == "added":
        added = added_pose_errors(
            http, runner.map_id, "bootstrap", images, first_frame_truth(images, images[0])
        )
        runner.index_references(len(images))  # as after a bulk load: the same as the map's
        figures["queries"] = localize_queries(
            runner, queries, first_frame_truth(queries, images[0])
        )
    return figures, added


def _cm(value: float | None) -> str:
    return "–" if value is None else f"{value * 100:.1f}"


def _deg(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}"


def _count(value: int | None) -> str:
    return "–" if value is None else str(value)


def _seconds(value: float | None) -> str:
    return "–" if value is None else f"{value:.0f}"


def _query_row(dataset: str, when: str, figures: dict[str, Any]) -> str:
    recalls = " | ".join(
        f"{figures['recall'][recall_key(m, d)] * 100:.0f}" for m, d in QUERY_THRESHOLDS
    )
    return (
        f"| {dataset} | {when} | {figures['localized']}/{figures['queries']} | {recalls} "
        f"| {_cm(figures['median_position_m'])} |"
    )


def markdown(results: dict[str, dict[str, Any]]) -> str:
    recall_heads = " | ".join(f"({m * 100:g} cm, {d:g}°) %" for m, d in QUERY_THRESHOLDS)
    lines = [
        "### Queries",
        "",
        f"| dataset | map | localized | {recall_heads} | median cm |",
        "|---|---|---|---|---|---|",
    ]
    for name, result in results.items():
        if "queries_before" not in result:  # --stale-only
            continue
        lines.append(_query_row(name, "before the session", result["queries_before"]))
        lines.append(_query_row(name, "after the session", result["queries_after"]))
        if "queries" in result.get("bootstrap", {}):
            lines.append(
                _query_row(name, "bootstrapped by a session", result["bootstrap"]["queries"])
            )
    lines += [
        "",
        "### Sessions",
        "",
        "| dataset | session | frames | expected | state | scale | agreeing / confident "
        "/ checked | rms cm | rms ° | upload s | job s | reason |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, result in results.items():
        for label, s in result.get("sessions", {}).items():
            flag = "" if s["state"] == s["expected"] else " ⚠"
            scale = "–" if s["scale"] is None else f"{s['scale']:.4f}"
            lines.append(
                f"| {name} | {label} | {s['frames']} | {s['expected']} | {s['state']}{flag} "
                f"| {scale} | {_count(s['agreeing'])} / {_count(s['confident'])} / {s['checked']} "
                f"| {_cm(s['rms_position_m'])} | {_deg(s['rms_rotation_deg'])} "
                f"| {_seconds(s['upload_s'])} | {_seconds(s['job_s'])} "
                f"| {s['reason'] or s['error'] or ''} |"
            )
    right_m, right_deg = ADDED_RIGHT
    lines += [
        "",
        "### Poses the frames were added with (against the ground truth)",
        "",
        "| dataset | session | found | median cm | p90 cm | max cm | median ° | p90 ° | max ° "
        f"| within ({right_m * 100:g} cm, {right_deg:g}°) % |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, result in results.items():
        for label, a in result.get("added", {}).items():
            if not a:
                continue
            p, r = a["position_m"], a["rotation_deg"]
            lines.append(
                f"| {name} | {label} | {a['found']}/{a['frames']} | {_cm(p['median'])} "
                f"| {_cm(p['p90'])} | {_cm(p['max'])} | {_deg(r['median'])} | {_deg(r['p90'])} "
                f"| {_deg(r['max'])} | {a['within'] * 100:.0f} |"
            )
    lines += [
        "",
        "### Stale references (references the session covers best, showing another place)",
        "",
        "| dataset | flagged by | state | swapped | flagged stale | found | false flags |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, result in results.items():
        st = result.get("stale")
        if st:
            ev = st["evaluation"]
            for by, state, figures in (
                (f"self-evaluation ({ev['held_out']} held out)", ev["state"], ev),
                (f"session {st['session_rule']}", st["state"], st),
            ):
                lines.append(
                    f"| {name} | {by} | {state} | {', '.join(st['swapped'])} "
                    f"| {', '.join(figures['flagged']) or '–'} "
                    f"| {figures['found']} of {len(st['swapped'])} | {figures['false_flags']} |"
                )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--dataset",
        action="append",
        choices=sorted(SCENARIOS),
        help="repeatable (default: redkitchen)",
    )
    parser.add_argument("--preset", default="xfeat-lg", help="the maps' features.preset")
    parser.add_argument(
        "--session-every", type=int, default=1, help="take every Nth frame of the session"
    )
    parser.add_argument(
        "--drift",
        type=float,
        default=0.01,
        help="position drift of the session's poses, a fraction of the distance travelled",
    )
    parser.add_argument(
        "--yaw-drift",
        type=float,
        default=0.05,
        help="rotation drift about the vertical, degrees per metre travelled",
    )
    parser.add_argument("--seed", type=int, default=0, help="seeds the drift's direction")
    parser.add_argument(
        "--no-depth", action="store_true", help="send no depth with references and frames"
    )
    parser.add_argument(
        "--quick", action="store_true", help="10 map frames, 10 session frames, 5 queries"
    )
    parser.add_argument(
        "--session",
        action="append",
        default=[],
        metavar="DATASET=RULE",
        help='another session rule for a dataset, e.g. "kitti05=range:120-224" (a session '
        "that overlaps the map)",
    )
    parser.add_argument(
        "--stale-only", action="store_true", help="only the stale-references scenario"
    )
    parser.add_argument(
        "--evaluation-sample",
        type=int,
        help="references the stale scenario's self-evaluation holds out (default: the server's)",
    )
    parser.add_argument("--datasets-dir", type=Path, default=Path("../shared/datasets"))
    parser.add_argument("--out", type=Path, default=Path("out/capture-sessions"))
    args = parser.parse_args(argv)
    if args.session_every < 1:
        parser.error("--session-every must be at least 1")
    sessions = dict(rule.split("=", 1) for rule in args.session if "=" in rule)
    if len(sessions) != len(args.session) or not set(sessions) <= set(SCENARIOS):
        parser.error(f"--session takes DATASET=RULE, DATASET one of {', '.join(SCENARIOS)}")
    options = Options(
        preset=args.preset,
        session_every=args.session_every,
        drift=args.drift,
        yaw_drift_deg_per_m=args.yaw_drift,
        seed=args.seed,
        depth=not args.no_depth,
        quick=args.quick,
        datasets_dir=args.datasets_dir,
        sessions=sessions,
        scratch=args.out,
        stale_only=args.stale_only,
        evaluation_sample=args.evaluation_sample,
    )
    env = {"SLLOC_AUTO_EVALUATION_REFERENCES": "0", "SLLOC_FEATURES": args.preset}
    results: dict[str, dict[str, Any]] = {}
    for name in args.dataset or ["redkitchen"]:
        start = time.perf_counter()
        with LocalServer(env) as server:
            try:
                results[name] = measure(name, server.url, options)
            except (SessionApiError, RuntimeError):
                _log(f"server log (end):\n{server.log_text()[-4000:]}")
                raise
        results[name]["seconds"] = time.perf_counter() - start
        _log(f"{name}: done in {results[name]['seconds']:.0f} s")
    args.out.mkdir(parents=True, exist_ok=True)
    meta = {
        "preset": args.preset,
        "session_every": args.session_every,
        "drift": args.drift,
        "yaw_drift_deg_per_m": args.yaw_drift,
        "seed": args.seed,
        "depth": not args.no_depth,
        "quick": args.quick,
        "sessions": sessions,
    }
    (args.out / "results.json").write_text(
        json.dumps({"options": meta, "datasets": results}, indent=1)
    )
    print(markdown(results))
    _log(f"wrote {args.out / 'results.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
