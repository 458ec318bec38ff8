"""Where a feature configuration's resident memory goes, per onnxruntime memory setting.

For each setting of the CPU arena (``enable_cpu_mem_arena``) and memory patterns
(``enable_mem_pattern``), a fresh process builds the configuration's extractor and matcher
on one thread per operation, extracts redkitchen frames and matches each query against ten
references as a localize request does, and prints its resident memory (VmRSS) after each
step, its peak (VmHWM) and the median time per query (extract + match). Run from the
repository root after ``scripts/build_models.sh``::

    .venv/bin/python -m tools.benchmarks.memory [--features aliked] [--queries 8]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from services.components import ModelStore, build_features
from services.features.configs import get_feature_config
from services.runtime.onnx import OnnxOptions
from services.runtime.threads import apply_thread_plan, plan_threads
from tools.evaluation.datasets import redkitchen_dataset
from tools.evaluation.server import memory_mb

SETTINGS = {  # label → (memory_arena, memory_pattern)
    "arena + patterns (onnxruntime default)": (True, True),
    "arena, no patterns": (True, False),
    "no arena, patterns": (False, True),
    "no arena, no patterns": (False, False),
}
REFERENCES_PER_QUERY = 10


def _rss() -> float:
    return memory_mb(os.getpid(), "VmRSS") or float("nan")


def measure(
    features: str, models_dir: Path, dataset: Path, queries: int, arena: bool, pattern: bool
) -> dict[str, float]:
    """Resident MiB after each step, the peak, and the median ms per query, in this
    process."""
    apply_thread_plan(plan_threads(workers=1, threads_per_worker=1))
    out = {"start": _rss()}
    onnx = OnnxOptions(intra_op_threads=1, memory_arena=arena, memory_pattern=pattern)
    extractor, matcher = build_features(get_feature_config(features), ModelStore(models_dir, onnx))
    out["models loaded"] = _rss()
    images = redkitchen_dataset(dataset).images
    refs = [images[i] for i in range(0, 500, 50)][:REFERENCES_PER_QUERY]
    query_images = [images[i] for i in range(500, 1000, 500 // queries)][:queries]

    def load(path: Path) -> np.ndarray:
        bgr = cv2.imread(str(path))
        if bgr is None:
            raise OSError(f"cannot read {path}")
        return np.ascontiguousarray(bgr[:, :, ::-1])

    ref_features = [extractor.extract(load(r.image_path)) for r in refs]
    out["references extracted"] = _rss()
    per_query = []
    for query in query_images:
        start = time.perf_counter()
        matcher.match_many(extractor.extract(load(query.image_path)), ref_features)
        per_query.append((time.perf_counter() - start) * 1000.0)
    out["queries localized"] = _rss()
    out["peak"] = memory_mb(os.getpid()) or float("nan")
    out["ms per query"] = float(np.median(per_query))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    root = Path(__file__).resolve().parents[2]
    parser.add_argument("--features", default="aliked", help="feature configuration")
    parser.add_argument(
        "--dataset", type=Path, default=root / ".." / "shared" / "datasets" / "redkitchen"
    )
    parser.add_argument("--models-dir", type=Path, default=root / "models")
    parser.add_argument("--queries", type=int, default=8)
    parser.add_argument("--child", help=argparse.SUPPRESS)  # "arena,pattern" as 0/1
    args = parser.parse_args()
    if args.child:
        arena, pattern = (bool(int(v)) for v in args.child.split(","))
        figures = measure(
            args.features, args.models_dir, args.dataset, args.queries, arena, pattern
        )
        print(json.dumps(figures))
        return
    steps: list[str] = []
    rows = []
    for label, (arena, pattern) in SETTINGS.items():
        child_args = ["--child", f"{int(arena)},{int(pattern)}"]
        child = subprocess.run(
            [sys.executable, "-m", "tools.benchmarks.memory", *sys.argv[1:], *child_args],
            check=True,
            capture_output=True,
            text=True,
        )
        figures = json.loads(child.stdout.strip().splitlines()[-1])
        steps = list(figures)
        rows.append(f"| {label} | " + " | ".join(f"{figures[s]:.0f}" for s in steps) + " |")
        print(rows[-1], flush=True)
    print(f"\n{args.features}, one thread; resident MiB after each step, peak, ms per query")
    print("| onnxruntime memory | " + " | ".join(steps) + " |")
    print("|---" * (len(steps) + 1) + "|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
