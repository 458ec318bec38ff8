"""The server's peak resident memory under worst-case localize requests, against its memory
bound (``services/runtime/memory.py``).

A map of ``--references`` synthetic references (textured 1024² images, ``--keypoints`` per
image) is built on a ``slloc serve`` with SQLite; a query of ``--pixels`` with a depth map
of as many pixels (16-bit PNG) is localized against ``--top-k`` of them (by default all;
fewer, and the unsure answer is matched again against as many others, the wider
retrieval). Two measurements, each on a fresh server of the map:

- one worker, no reference caches: each of ``--repeats`` localizes' peak (``VmHWM``, reset
  through ``/proc/<pid>/clear_refs`` before the request) over the resident size before it,
  against the memory the bound counts for one largest request (its ``computing`` term);
- the default settings (the workers of the thread plan, the caches on): the peak while
  ``--clients`` send the query at once, ``--repeats`` rounds, against the whole bound.

Self-evaluations are off (``SLLOC_AUTO_EVALUATION_REFERENCES=0``); the bound comes from the
server's ``GET /v1/health``::

    python -m tools.benchmarks.worst_request [--features sift] [--references 50] \\
        [--top-k 50] [--keypoints 4096] [--pixels 12582912] [--repeats 3]
"""

from __future__ import annotations

import argparse
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np

from app.schemas.geometry import CameraSchema
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from tools.benchmarks.memory_terms import textured_image
from tools.evaluation.datasets import PosedImage
from tools.evaluation.runner import HttpRunner
from tools.evaluation.server import LocalServer, memory_mb, reset_peak

REFERENCE_SIDE = 1024
# the bound's term for the requests computing at once: at least one largest request
COMPUTING_TERM = "computing"


def _camera(width: int, height: int) -> Camera:
    focal = 0.8 * max(width, height)
    return Camera("PINHOLE", width, height, (focal, focal, width / 2, height / 2))


def _jpeg(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    return data.tobytes()


def _references(folder: Path, count: int) -> list[PosedImage]:
    """``count`` textured views on a ring of radius 2 m, each looking at its centre."""
    images = []
    for i in range(count):
        path = folder / f"ref{i:04d}.jpg"
        path.write_bytes(_jpeg(textured_image(REFERENCE_SIDE, seed=i)))
        angle = 2 * np.pi * i / count
        center = np.array([2 * np.sin(angle), 0.0, -2 * np.cos(angle)])
        z = -center / np.linalg.norm(center)
        x = np.cross([0.0, 1.0, 0.0], z)
        rotation = np.stack([x, np.cross(z, x), z])
        images.append(
            PosedImage(
                path.name,
                path,
                _camera(REFERENCE_SIDE, REFERENCE_SIDE),
                Rigid3d(rotation, -rotation @ center),
            )
        )
    return images


def _size(pixels: int) -> tuple[int, int]:
    """The largest 4:3 image of at most ``pixels``: (width, height)."""
    unit = int(np.sqrt(pixels / 12))
    return 4 * unit, 3 * unit


def _query(pixels: int) -> tuple[bytes, bytes, Camera]:
    """A 4:3 textured JPEG of at most ``pixels`` and a 16-bit depth PNG of as many."""
    width, height = _size(pixels)
    texture = cv2.resize(
        textured_image(1024, seed=10**6), (width, height), interpolation=cv2.INTER_CUBIC
    )
    depth = np.full((height, width), 2000, np.uint16)  # millimetres
    ok, png = cv2.imencode(".png", depth)
    assert ok
    return _jpeg(texture), png.tobytes(), _camera(width, height)


def build_map(env: dict[str, str], folder: Path, args: argparse.Namespace) -> str:
    """The synthetic map, its retrieval vocabulary trained; its id."""
    with LocalServer(env) as server:
        runner = HttpRunner(
            server.url,
            None,
            "worst-request",
            keep_map=True,
            features={"preset": args.features, "max_keypoints": args.keypoints},
        )
        for reference in _references(folder, args.references):
            runner.add_reference(reference, None)
        runner.index_references(args.references)
        runner.close()
        return runner.map_id


def _params(camera: Camera, top_k: int) -> dict[str, Any]:
    return {
        "camera": CameraSchema.from_camera(camera).model_dump(),
        "top_k": top_k,
        "time_budget_s": 10,
    }


def one_worker(
    env: dict[str, str], map_id: str, args: argparse.Namespace
) -> tuple[list[float], float]:
    """Each localize's peak over the resident size before it, on a fresh server of one
    worker without reference caches (its heap holds nothing freed by the adds); and the
    bound's computing term."""
    env = {
        **env,
        "SLLOC_LOCALIZE_WORKERS": "1",
        "SLLOC_REFERENCE_CACHE_MIB": "0",
        "SLLOC_REFERENCE_IMAGE_CACHE_MIB": "0",
    }
    with LocalServer(env) as server:
        health = httpx.get(f"{server.url}/v1/health", timeout=10).json()
        computing = health["runtime"]["memory_terms_mib"][COMPUTING_TERM]
        runner = HttpRunner(server.url, None, map_id=map_id)
        image, depth, camera = _query(args.pixels)
        added = []
        for _ in range(args.repeats):
            before = memory_mb(server.pid, "VmRSS") or float("nan")
            reset_peak(server.pid)
            outcome = runner.localize(image, depth, _params(camera, args.top_k))
            added.append((memory_mb(server.pid) or float("nan")) - before)
            print(
                f"one worker: {outcome.reason or 'localized'}, peak +{added[-1]:.0f} MiB over "
                f"{before:.0f} MiB resident",
                flush=True,
            )
        runner.close()
        return added, computing


def whole_server(
    env: dict[str, str], map_id: str, args: argparse.Namespace
) -> tuple[float, float, int]:
    """The peak resident memory of a server with the default settings while ``--clients``
    send the worst-case localize at once, ``--repeats`` rounds; its memory bound and
    localize workers (``GET /v1/health``)."""
    with LocalServer(env) as server:
        runtime = httpx.get(f"{server.url}/v1/health", timeout=10).json()["runtime"]
        runner = HttpRunner(server.url, None, map_id=map_id)
        image, depth, camera = _query(args.pixels)
        params = _params(camera, args.top_k)
        with ThreadPoolExecutor(args.clients) as pool:
            for round_ in range(args.repeats):
                outcomes = list(
                    pool.map(lambda _: runner.localize(image, depth, params), range(args.clients))
                )
                reasons = ", ".join(o.reason or "localized" for o in outcomes)
                peak = memory_mb(server.pid) or float("nan")
                print(f"whole server, round {round_ + 1}: {reasons}; peak {peak:.0f} MiB")
        runner.close()
        return peak, runtime["memory_bound_mib"], runtime["localize_workers"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--features", default="sift", help="the map's feature configuration")
    parser.add_argument("--references", type=int, default=50, help="the map's references")
    parser.add_argument("--top-k", type=int, default=None, help="default: all the references")
    parser.add_argument("--keypoints", type=int, default=4096, help="the map's max_keypoints")
    parser.add_argument(
        "--pixels", type=int, default=4096 * 3072, help="the query's (the default pixel limit)"
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--clients", type=int, default=4, help="concurrent localizes")
    args = parser.parse_args()
    args.top_k = args.top_k or args.references
    with tempfile.TemporaryDirectory() as folder:
        env = {
            "SLLOC_DATABASE_URL": f"sqlite:///{folder}/slloc.db",
            "SLLOC_FEATURES": args.features,
            "SLLOC_AUTO_EVALUATION_REFERENCES": "0",
        }
        map_id = build_map(env, Path(folder), args)
        added, computing = one_worker(env, map_id, args)
        peak, bound, workers = whole_server(env, map_id, args)
    width, height = _size(args.pixels)
    print(
        f"\n{args.features}, {args.references} references of {args.keypoints} keypoints, "
        f"query {width}×{height} with a depth map, top_k {args.top_k}\n"
    )
    print("| | measured peak | bound | bound / peak |")
    print("|---|---|---|---|")
    print(
        f"| one localize, one worker (max of {args.repeats}) | +{max(added):.0f} MiB | "
        f"{computing:.0f} MiB (computing) | {computing / max(added):.2f} |"
    )
    print(
        f"| the server, {args.clients} clients, {workers} workers | {peak:.0f} MiB | "
        f"{bound:.0f} MiB | {bound / peak:.2f} |"
    )


if __name__ == "__main__":
    main()
