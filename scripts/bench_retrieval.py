"""Retrieval: top-10 search time over large maps, and recall@k on redkitchen.

1. Search: ``top_k`` over 1k / 10k / 100k random unit descriptors (the thumbnail's 768
   dimensions and a compact 256), median and p90 ms over 50 queries, and the index memory.
2. Recall@k (k = 1, 5, 10) of the thumbnail descriptor on redkitchen's suggested split
   (references frames 0…499 every 5th, queries 500…999 every 10th): a query counts when a
   top-k reference lies within 0.5 m and 30° of it, over the queries that have such a
   reference at all.

Run from the repository root: ``.venv/bin/python scripts/bench_retrieval.py [--dataset DIR]``
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from app.evaluation.datasets import redkitchen_dataset
from services.features.base import LocalFeatures
from services.geometry.rigid import rotation_error_deg
from services.retrieval.search import top_k
from services.retrieval.thumbnail import ThumbnailDescriptor

NEAR_M, NEAR_DEG = 0.5, 30.0


def search_times(rng: np.random.Generator) -> None:
    print("| references | dims | median ms | p90 ms | index MiB |")
    print("|---|---|---|---|---|")
    for n in (1_000, 10_000, 100_000):
        for dims in (768, 256):
            rows = rng.normal(size=(n, dims)).astype(np.float32)
            rows /= np.linalg.norm(rows, axis=1, keepdims=True)
            times = []
            for q in rng.integers(0, n, 50):
                query = rows[q] + 0.05 * rng.normal(size=dims).astype(np.float32)
                query /= np.linalg.norm(query)
                start = time.perf_counter()
                top_k(query, rows, 10)
                times.append((time.perf_counter() - start) * 1000)
            print(
                f"| {n} | {dims} | {np.median(times):.2f} | {np.percentile(times, 90):.2f} | "
                f"{rows.nbytes / 2**20:.0f} |",
                flush=True,
            )


def recall(dataset: Path) -> None:
    images = redkitchen_dataset(dataset).images
    references = images[0:500:5]
    queries = images[500:1000:10]
    descriptor = ThumbnailDescriptor()
    no_features = LocalFeatures(
        np.zeros((0, 2), np.float32),
        np.zeros((0, 128), np.float32),
        np.zeros(0, np.float32),
        (0, 0),
    )

    def describe(path: Path) -> np.ndarray:
        rgb = np.ascontiguousarray(cv2.imread(str(path))[:, :, ::-1])
        return descriptor.compute(rgb, no_features)

    table = np.stack([describe(r.image_path) for r in references])
    centers = np.stack([r.cam_from_world.center for r in references])
    hits = {1: 0, 5: 0, 10: 0}
    counted = 0
    for query in queries:
        near = np.array(
            [
                np.linalg.norm(c - query.cam_from_world.center) <= NEAR_M
                and rotation_error_deg(r.cam_from_world.rotation, query.cam_from_world.rotation)
                <= NEAR_DEG
                for r, c in zip(references, centers, strict=True)
            ]
        )
        if not near.any():
            continue
        counted += 1
        rows, _ = top_k(describe(query.image_path), table, 10)
        for k in hits:
            hits[k] += bool(near[rows[:k]].any())
    print(
        f"\n{descriptor.name}: {counted} of {len(queries)} queries have a reference within "
        f"{NEAR_M} m and {NEAR_DEG:g}°"
    )
    for k, h in hits.items():
        print(f"recall@{k}: {100 * h / counted:.1f} % ({h}/{counted})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    root = Path(__file__).resolve().parents[1]
    parser.add_argument(
        "--dataset", type=Path, default=root / ".." / "shared" / "datasets" / "redkitchen"
    )
    args = parser.parse_args()
    search_times(np.random.default_rng(0))
    recall(args.dataset)


if __name__ == "__main__":
    main()
