"""Time and peak memory of adding and localizing a huge JPEG, decoded reduced or in full.

A redkitchen frame (or the synthetic scene's first view) is enlarged to ``--width`` ×
``--height`` (7200×5400 by default) and encoded as a JPEG; for each decoding mode a fresh
process builds the localizer, describes it as a reference three times and localizes it
against those references, and prints the median milliseconds of each and the process's peak
resident memory (VmHWM) above what the localizer itself held. ``full`` decodes every pixel
(what the service did before reduced decoding); ``reduced`` lets libjpeg decode at 1/2, 1/4
or 1/8 scale while the image stays at least the extractor's ``max_side``. Run from the
repository root::

    .venv/bin/python -m tools.benchmarks.large_jpeg [--features aliked] [--models models]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import cv2

from services.components import EngineConfig, build_localizer
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.imaging.decode import DecodedImage, decode_image_reduced
from services.localization import localizer as single_frame
from services.localization.localizer import LocalizeParams
from services.references.memory import MemoryReferenceStore
from tools.evaluation.server import memory_mb
from tools.synthetic.scene import SyntheticScene

REDKITCHEN_FRAME = Path("/work/shared/datasets/redkitchen/images/frame-000000.color.jpg")
MODES = ("full", "reduced")
ROUNDS = 3


def _decode_in_full(data: bytes, max_pixels: int, min_side: int | None) -> DecodedImage:
    return decode_image_reduced(data, max_pixels, None)


def _large_jpeg(width: int, height: int) -> tuple[bytes, Camera]:
    """The test image enlarged to width × height, as a JPEG, and its pinhole camera."""
    frame = cv2.imread(str(REDKITCHEN_FRAME)) if REDKITCHEN_FRAME.is_file() else None
    if frame is not None:
        bgr = frame
        f, cx, cy = 525.0, 320.0, 240.0
    else:
        view = SyntheticScene(seed=0).views(1, stream=1, prefix="ref")[0]
        bgr = cv2.cvtColor(view.image, cv2.COLOR_RGB2BGR)
        f, cx, cy = view.camera.params[0], view.camera.params[2], view.camera.params[3]
    sx, sy = width / bgr.shape[1], height / bgr.shape[0]
    big = cv2.resize(bgr, (width, height), interpolation=cv2.INTER_CUBIC)
    ok, data = cv2.imencode(".jpg", big, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    return data.tobytes(), Camera("PINHOLE", width, height, (f * sx, f * sy, cx * sx, cy * sy))


def measure(
    mode: str, features: str | None, models: Path, width: int, height: int
) -> dict[str, object]:
    """Median ms of add (describe) and localize, and peak MiB above the built localizer."""
    data, camera = _large_jpeg(width, height)
    localizer = build_localizer(
        EngineConfig.resolve(models, max_pixels=width * height, features=features)
    )
    if mode == "full":  # what the pipeline did before reduced decoding
        vars(single_frame)["decode_image_reduced"] = _decode_in_full
    pid = os.getpid()
    base = memory_mb(pid, "VmRSS") or 0.0
    store = MemoryReferenceStore()
    add_ms = []
    for i in range(ROUNDS):
        start = time.perf_counter()
        reference = localizer.describe_reference(data, camera)
        add_ms.append(1000 * (time.perf_counter() - start))
        store.add(f"ref{i}", camera, Rigid3d.identity(), reference)
    localize_ms = []
    for _ in range(ROUNDS):
        start = time.perf_counter()
        result = localizer.localize(data, LocalizeParams(camera=camera), store)
        localize_ms.append(1000 * (time.perf_counter() - start))
    return {
        "mode": mode,
        "features": localizer.extractor.name,
        "image": f"{width}x{height}, {len(data) / 1e6:.1f} MB",
        "add_ms": round(statistics.median(add_ms)),
        "localize_ms": round(statistics.median(localize_ms)),
        "peak_mib_above_localizer": round((memory_mb(pid) or 0.0) - base),
        "keypoints": len(reference.features),
        "localized": result.localized,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--features", default=None, help="feature configuration (default: auto)")
    parser.add_argument("--models", type=Path, default=Path("models"))
    parser.add_argument("--width", type=int, default=7200)
    parser.add_argument("--height", type=int, default=5400)
    parser.add_argument("--mode", choices=MODES, help=argparse.SUPPRESS)  # one child's run
    args = parser.parse_args()
    if args.mode is not None:
        print(json.dumps(measure(args.mode, args.features, args.models, args.width, args.height)))
        return 0
    for mode in MODES:  # each in a fresh process: VmHWM is per process
        command = [sys.executable, "-m", "tools.benchmarks.large_jpeg", "--mode", mode]
        command += ["--models", str(args.models), "--width", str(args.width)]
        command += ["--height", str(args.height)]
        if args.features:
            command += ["--features", args.features]
        out = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        print(out.strip().splitlines()[-1], flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
