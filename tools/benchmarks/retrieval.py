"""Retrieval: top-10 search time over large maps, and recall@k on redkitchen.

1. Search: ``top_k`` over 1k / 10k / 100k random unit descriptors (the service's VLAD,
   K = 8 × 128 = 1024 dimensions, and the thumbnail's 768), median and p90 ms over 50
   queries, and the index memory.
2. Recall@k (k = 1, 5, 10) on redkitchen's suggested split (references frames 0…499 every
   5th, queries 500…999 every 10th) of the thumbnail (small maps) and of VLAD over the map's
   own vocabulary of SIFT descriptors (K = 8 in the service; 16 for comparison) and, when
   ``xfeat`` is built in ``--models``, of XFeat's 2048 64-D descriptors (K = 8 … 64; the
   service uses ``policy.num_centers``): a query counts when a top-k reference lies within
   0.5 m and 30° of it, over the queries that have such a reference at all.

Run from the repository root: ``.venv/bin/python -m tools.benchmarks.retrieval [--dataset DIR]``
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np

from services.components import ModelsMissingError, ModelStore, build_features
from services.features.base import LocalFeatures
from services.features.configs import get_feature_config
from services.features.sift import SiftExtractor
from services.geometry.rigid import rotation_error_deg
from services.retrieval.policy import NUM_CENTERS
from services.retrieval.search import top_k
from services.retrieval.thumbnail import ThumbnailDescriptor
from services.retrieval.vlad import Vocabulary, encode, train_vocabulary
from services.types import Float32Array
from tools.benchmarks.images import load_rgb
from tools.evaluation.datasets import redkitchen_dataset

NEAR_M, NEAR_DEG = 0.5, 30.0


def search_times(rng: np.random.Generator) -> None:
    print("| references | dims | median ms | p90 ms | index MiB |")
    print("|---|---|---|---|---|")
    for n in (1_000, 10_000, 100_000):
        for dims in (NUM_CENTERS * 128, 768):
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


def recall(dataset: Path, models: Path) -> None:
    images = redkitchen_dataset(dataset).images
    references = images[0:500:5]
    queries = images[500:1000:10]
    rgb = {i.name: load_rgb(i.image_path) for i in references + queries}
    sift = SiftExtractor()
    features = {name: sift.extract(image) for name, image in rgb.items()}
    thumbnail = ThumbnailDescriptor()
    describers: dict[str, Callable[[str], Float32Array]] = {
        thumbnail.name: lambda name: thumbnail.compute(rgb[name], features[name])
    }
    sweeps: list[tuple[str, dict[str, LocalFeatures], tuple[int, ...]]] = [
        ("sift", features, (NUM_CENTERS, 16))
    ]
    try:
        xfeat, _ = build_features(get_feature_config("xfeat"), ModelStore(models))
        sweeps.append(("xfeat", {n: xfeat.extract(i) for n, i in rgb.items()}, (8, 16, 32, 64)))
    except ModelsMissingError as exc:
        print(f"xfeat left out: {exc}")
    for label, described, centers_tried in sweeps:
        for centers in centers_tried:
            vocabulary = train_vocabulary(
                [described[r.name].descriptors for r in references], num_centers=centers
            )
            describers[f"vlad-{label}-k{centers}"] = partial(_vlad, described, vocabulary)

    near = [
        np.array(
            [
                np.linalg.norm(r.cam_from_world.center - q.cam_from_world.center) <= NEAR_M
                and rotation_error_deg(r.cam_from_world.rotation, q.cam_from_world.rotation)
                <= NEAR_DEG
                for r in references
            ]
        )
        for q in queries
    ]
    counted = sum(bool(n.any()) for n in near)
    print(
        f"\n{counted} of {len(queries)} queries have a reference within {NEAR_M} m and "
        f"{NEAR_DEG:g}°; recall over those:\n"
    )
    print("| descriptor | dims | recall@1 | recall@5 | recall@10 |")
    print("|---|---|---|---|---|")
    for label, describe in describers.items():
        table = np.stack([describe(r.name) for r in references])
        hits = {1: 0, 5: 0, 10: 0}
        for query, ok in zip(queries, near, strict=True):
            if ok.any():
                rows, _ = top_k(describe(query.name), table, 10)
                for k in hits:
                    hits[k] += bool(ok[rows[:k]].any())
        cells = " | ".join(f"{100 * h / counted:.1f} %" for h in hits.values())
        print(f"| {label} | {table.shape[1]} | {cells} |", flush=True)


def _vlad(features: dict[str, LocalFeatures], vocabulary: Vocabulary, name: str) -> Float32Array:
    return encode(features[name].descriptors, vocabulary)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    root = Path(__file__).resolve().parents[2]
    parser.add_argument(
        "--dataset", type=Path, default=root / ".." / "shared" / "datasets" / "redkitchen"
    )
    parser.add_argument("--models", type=Path, default=root / "models")
    args = parser.parse_args()
    search_times(np.random.default_rng(0))
    recall(args.dataset, args.models)


if __name__ == "__main__":
    main()
