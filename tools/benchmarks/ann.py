"""The approximate retrieval index (``services/retrieval/ann.py``, faiss IVF-SQ8) over a
million references: top-10 p50/p90 latency, recall@10 against exact search, build time and
memory.

Data: synthetic unit vectors of the service's VLAD length (8 centres × 128-D = 1024-D). Pure
i.i.d. random vectors have no neighbourhood structure (every pair is nearly orthogonal, which
no real map looks like), so references are drawn around ``--places`` random place vectors
(``normalize(place + noise)``, cosine ≈ 0.5 between two views of one place) and each query is
a new view of a random place; its exact top-10 are views of that place. The vectors are made
in chunks, so the exact top-10 are found without holding the 4 GiB float32 matrix.

Usage: python -m tools.benchmarks.ann [--references 1000000] [--queries 200]
       [--nprobe 16 32 64 128 256]
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import faiss
import numpy as np

from services.retrieval.ann import AnnIndex, AnnOptions
from tools.synthetic.descriptors import place_views, unit_rows

DIM = 1024
CHUNK = 100_000


def _rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--references", type=int, default=1_000_000)
    parser.add_argument("--queries", type=int, default=200)
    parser.add_argument("--places", type=int, default=20_000)
    parser.add_argument(
        "--nprobe", type=int, nargs="+", default=[16, 32, 64, 128, 256], help="values to sweep"
    )
    args = parser.parse_args()
    n, k = args.references, 10
    rng = np.random.default_rng(0)
    places = unit_rows(rng, args.places, DIM)
    queries = place_views(rng, places, rng.integers(0, args.places, args.queries))
    options = AnnOptions(min_references=1, nprobe=args.nprobe[0])

    rss_before = _rss_mib()
    build_s = 0.0
    best_scores = np.full((args.queries, k), -np.inf, np.float32)
    best_ids = np.zeros((args.queries, k), np.int64)
    index: AnnIndex | None = None
    for first in range(0, n, CHUNK):
        chunk = place_views(rng, places, rng.integers(0, args.places, min(CHUNK, n - first)))
        scores = queries @ chunk.T  # exact search, merged chunk by chunk
        merged_scores = np.concatenate([best_scores, scores], axis=1)
        merged_ids = np.concatenate(
            [best_ids, np.broadcast_to(np.arange(first, first + chunk.shape[0]), scores.shape)],
            axis=1,
        )
        top = np.argsort(-merged_scores, axis=1)[:, :k]
        best_scores = np.take_along_axis(merged_scores, top, 1)
        best_ids = np.take_along_axis(merged_ids, top, 1)
        start = time.perf_counter()
        if index is None:  # trained on the first chunk's sample, sized for the whole map
            index = AnnIndex(chunk, options, nlist=int(np.sqrt(n)))
        else:
            index.add(chunk)
        build_s += time.perf_counter() - start
        del chunk, scores
    assert index is not None
    rss_after = _rss_mib()

    faiss.omp_set_num_threads(1)  # one request searches on one thread
    sweep = []
    for nprobe in args.nprobe:
        index.options = AnnOptions(min_references=1, nprobe=nprobe)
        latencies, hits = [], 0
        for q in range(args.queries):
            start = time.perf_counter()
            slots, _ = index.search(queries[q], k)
            latencies.append((time.perf_counter() - start) * 1e3)
            hits += len(set(slots.tolist()) & set(best_ids[q].tolist()))
        sweep.append((nprobe, np.percentile(latencies, 50), np.percentile(latencies, 90), hits))
    exact_ms = []
    sample_rows = place_views(rng, places, rng.integers(0, args.places, min(n, CHUNK)))
    for q in range(min(20, args.queries)):  # exact search over one chunk, scaled to n
        start = time.perf_counter()
        np.argpartition(-(sample_rows @ queries[q]), k)[:k]
        exact_ms.append((time.perf_counter() - start) * 1e3 * n / sample_rows.shape[0])

    print(f"faiss {faiss.__version__}, IVF-SQ8, nlist {int(np.sqrt(n))}")
    print(f"references: {n} synthetic unit vectors, {DIM}-D (VLAD, 8 x 128), {args.places} places")
    print(f"build (train + add): {build_s:.1f} s")
    print(f"top-10 over {args.queries} queries, one thread:")
    print("| nprobe | p50 ms | p90 ms | recall@10 vs exact |")
    print("|---|---|---|---|")
    for nprobe, p50, p90, hits in sweep:
        print(f"| {nprobe} | {p50:.2f} | {p90:.2f} | {hits / (k * args.queries):.3f} |")
    print(
        f"exact search (numpy, extrapolated from {sample_rows.shape[0]}): "
        f"p50 {np.median(exact_ms):.0f} ms"
    )
    print(
        f"memory: index codes + ids {index.nbytes() / 2**20:.0f} MiB; process RSS grew "
        f"{rss_after - rss_before:.0f} MiB while building (peak RSS "
        f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB); the float32 "
        f"matrix exact search needs: {n * DIM * 4 / 2**20:.0f} MiB"
    )


if __name__ == "__main__":
    main()
