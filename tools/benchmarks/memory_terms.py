"""The per-operation memory the service's bound (``services/runtime/memory.py``) is made of,
measured one operation per fresh process: the peak resident memory (VmHWM) it adds to a
process that already holds what it needs.

- ``runtime``: the interpreter with the service's libraries imported (``app.main``);
- ``models``: the feature configuration's ONNX sessions built on top of it;
- ``extract S``: one extraction of an S×S image at ``max_side`` S (default keypoint budget);
- ``match K``: a query matched as a localize does against ``--refs`` references of K
  keypoints (nearest neighbours on every pair, LightGlue on the configuration's pairs);
- ``decode P``: one full decode of a P-megapixel PNG (RGB uint8).

On one thread per operation, onnxruntime's memory arena off (the service's defaults). Run
from the repository root after ``scripts/build_models.sh``::

    .venv/bin/python -m tools.benchmarks.memory_terms [--features aliked]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

from tools.evaluation.server import memory_mb, reset_peak

SIDES = (640, 1024, 2048)
KEYPOINTS = (512, 1024, 2048)
MEGAPIXELS = (10, 40)


def _rss() -> float:
    return memory_mb(os.getpid(), "VmRSS") or float("nan")


def _peak() -> float:
    return memory_mb(os.getpid()) or float("nan")


def textured_image(side: int, seed: int = 0) -> np.ndarray:
    """A textured side×side RGB image (smoothed noise: keypoints everywhere)."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (max(8, side // 8), max(8, side // 8), 3), dtype=np.uint8)
    return np.ascontiguousarray(cv2.resize(small, (side, side), interpolation=cv2.INTER_CUBIC))


def measure(term: str, value: int, features: str, models_dir: Path, refs: int) -> float:
    """MiB the operation adds to this process's peak resident memory."""
    import app.main  # noqa: F401  (the service's libraries, as the server imports them)
    from services.components import ModelStore, build_features
    from services.features.configs import get_feature_config
    from services.runtime.onnx import OnnxOptions
    from services.runtime.threads import apply_thread_plan, plan_threads

    apply_thread_plan(plan_threads(workers=1, threads_per_worker=1))
    if term == "runtime":
        return _peak()
    if term == "decode":
        side = int(np.sqrt(value * 1e6))
        ok, png = cv2.imencode(".png", textured_image(side))
        assert ok
        data = png.tobytes()
        from services.imaging.decode import decode_image

        before = _rss()
        reset_peak(os.getpid())
        decode_image(data, 10**9)
        return _peak() - before
    config = get_feature_config(features)
    before = _rss()
    extractor, matcher = build_features(
        config, ModelStore(models_dir, OnnxOptions(intra_op_threads=1))
    )
    if term == "models":
        return _rss() - before
    if term == "extract":
        extractor = extractor.with_budget(None, value)
        image = textured_image(value)
        extractor.extract(textured_image(64 * 2))  # sessions initialised before the baseline
        before = _rss()
        reset_peak(os.getpid())
        extractor.extract(image)
        return _peak() - before
    if term == "match":
        from services.features.base import LocalFeatures

        rng = np.random.default_rng(1)
        dim = extractor.extract(textured_image(128)).descriptors.shape[1]

        def random_features() -> LocalFeatures:
            descriptors = rng.standard_normal((value, dim)).astype(np.float32)
            descriptors /= np.linalg.norm(descriptors, axis=1, keepdims=True)
            keypoints = rng.uniform(0, 2048, (value, 2)).astype(np.float32)
            return LocalFeatures(keypoints, descriptors, np.ones(value, np.float32), (2048, 2048))

        query, references = random_features(), [random_features() for _ in range(refs)]
        matcher.match(query, references[0])  # sessions initialised before the baseline
        before = _rss()
        reset_peak(os.getpid())
        matcher.match_many(query, references)
        return _peak() - before
    raise ValueError(f"unknown term {term}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    root = Path(__file__).resolve().parents[2]
    parser.add_argument("--features", default="aliked", help="feature configuration")
    parser.add_argument("--models-dir", type=Path, default=root / "models")
    parser.add_argument("--refs", type=int, default=10, help="references a query is matched to")
    parser.add_argument("--child", help=argparse.SUPPRESS)  # "term,value"
    args = parser.parse_args()
    if args.child:
        term, value = args.child.split(",")
        print(json.dumps(measure(term, int(value), args.features, args.models_dir, args.refs)))
        return
    plan = [("runtime", 0), ("models", 0)]
    plan += [("extract", s) for s in SIDES] + [("match", k) for k in KEYPOINTS]
    plan += [("decode", p) for p in MEGAPIXELS]
    print(f"{args.features}, one thread per operation; MiB added to the peak resident memory")
    command = [sys.executable, "-m", "tools.benchmarks.memory_terms", *sys.argv[1:]]
    for term, value in plan:
        child = subprocess.run(
            [*command, "--child", f"{term},{value}"],
            check=True,
            capture_output=True,
            text=True,
        )
        mib = json.loads(child.stdout.strip().splitlines()[-1])
        print(f"{term} {value}: {mib:.0f} MiB", flush=True)


if __name__ == "__main__":
    main()
