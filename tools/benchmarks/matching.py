"""Nearest-neighbour matching of SIFT features: its 8-bit integer similarities against float32.

For pairs of frames ``--gap`` apart (every ``--step``-th frame of the dataset), SIFT at the
``sift`` preset's budget, it prints the median time per pair of the service's matcher and of
the same mutual nearest-neighbour ratio test on a float32 product, and how many matches the
two share. Both run on the threads one of the service's workers has (one on two cores).
Run from the repository root::

    .venv/bin/python -m tools.benchmarks.matching ../shared/datasets/kitti05/frames.csv
    .venv/bin/python -m tools.benchmarks.matching ../shared/datasets/redkitchen --step 50
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from services.features.base import LocalFeatures
from services.features.sift import SiftExtractor
from services.matching.nearest_neighbor import NearestNeighborMatcher
from services.runtime.threads import apply_thread_plan, plan_threads
from services.types import Float32Array, FloatArray, IntArray
from tools.benchmarks.images import load_rgb
from tools.evaluation.datasets import open_dataset

RATIO = 0.8  # the sift preset's


def float_ratios(query: Float32Array, reference: Float32Array) -> tuple[IntArray, FloatArray]:
    """Each query descriptor's nearest reference descriptor on float32 cosines, and its
    distance ratio to the second nearest (inf where the two are not each other's nearest)."""
    similarity = query @ reference.T
    rows = np.arange(len(query))
    best = similarity.argmax(axis=1)
    first = similarity[rows, best].copy()
    mutual = first >= similarity.max(axis=0)[best]
    similarity[rows, best] = -np.inf
    second = similarity.max(axis=1)
    d_first = np.sqrt(np.maximum(2.0 - 2.0 * first, 0.0))
    d_second = np.sqrt(np.maximum(2.0 - 2.0 * second, 1e-12))
    return best, np.where(mutual, d_first / d_second, np.inf)


def float_matches(query: LocalFeatures, reference: LocalFeatures) -> IntArray:
    """The matcher's test on float32 cosines."""
    best, ratio = float_ratios(query.descriptors, reference.descriptors)
    keep = ratio < RATIO
    return np.stack([np.flatnonzero(keep), best[keep]], axis=1)


def _timed(
    match: Callable[[LocalFeatures, LocalFeatures], IntArray],
    query: LocalFeatures,
    reference: LocalFeatures,
    repeats: int = 3,
) -> tuple[IntArray, float]:
    """``match``'s matches and its median milliseconds."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = match(query, reference)
        times.append(time.perf_counter() - start)
    return out, 1e3 * float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("dataset", type=Path, help="an import .csv or a redkitchen folder")
    parser.add_argument("--step", type=int, default=15, help="every step-th frame starts a pair")
    parser.add_argument("--gap", type=int, default=3, help="frames between a pair's two")
    args = parser.parse_args()
    apply_thread_plan(plan_threads())
    images = open_dataset(args.dataset).images
    extractor = SiftExtractor()
    matcher = NearestNeighborMatcher(RATIO)
    rows = []
    for start in range(0, len(images) - args.gap, args.step):
        query, reference = (
            extractor.extract(load_rgb(images[i].image_path)) for i in (start, start + args.gap)
        )
        integer, integer_ms = _timed(matcher.match, query, reference)
        floating, float_ms = _timed(float_matches, query, reference)
        shared = len({tuple(m) for m in integer} & {tuple(m) for m in floating})
        rows.append((len(query) * len(reference), integer_ms, float_ms, len(floating), shared))
    pairs = np.array(rows, dtype=float)
    print(f"{len(pairs)} pairs of {args.dataset}, gap {args.gap}, {extractor.name}")
    print("| keypoint pairs | pairs | integer ms | float32 ms | float32 / integer |")
    print("|---|---|---|---|---|")
    for low, high in ((0, 4e6), (4e6, 9e6), (9e6, 17e6)):
        group = pairs[(pairs[:, 0] >= low) & (pairs[:, 0] < high)]
        if len(group):
            integer_ms, float_ms = np.median(group[:, 1]), np.median(group[:, 2])
            print(
                f"| {low / 1e6:g}–{high / 1e6:g} M | {len(group)} | {integer_ms:.1f} | "
                f"{float_ms:.1f} | {float_ms / integer_ms:.1f} |"
            )
    share = pairs[:, 4].sum() / pairs[:, 3].sum()
    print(f"float32 matches the integer matcher also makes: {100 * share:.1f} %")


if __name__ == "__main__":
    main()
