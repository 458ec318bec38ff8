"""The approximate retrieval index (``services/retrieval/ann.py``: faiss IVF-SQ8 candidates
rescored exactly) over a million references: top-10 p50/p90 latency, recall@10 against exact
search, build time and memory.

Data: synthetic unit vectors of the service's VLAD length (8 centres × 128-D = 1024-D). Pure
i.i.d. random vectors have no neighbourhood structure (every pair is nearly orthogonal, which
no real map looks like), so references are drawn around ``--places`` random place vectors
(``normalize(place + noise)``, cosine ≈ 0.5 between two views of one place) and each query is
a new view of a random place; its exact top-10 are views of that place. The float32 matrix is
held as the service holds it (``RetrievalIndex.descriptors``, which rescores the candidates).

Usage: python -m tools.benchmarks.ann [--references 1000000] [--queries 200]
       [--nprobe 32 64 128 256] [--rerank 1 4]
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import faiss
import numpy as np
from threadpoolctl import threadpool_limits

from services.retrieval.ann import AnnOptions, AnnView
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
        "--nprobe", type=int, nargs="+", default=[32, 64, 128, 256], help="values to sweep"
    )
    parser.add_argument(
        "--rerank", type=int, nargs="+", default=[1, 4], help="candidates per result to sweep"
    )
    args = parser.parse_args()
    n, k = args.references, 10
    rng = np.random.default_rng(0)
    places = unit_rows(rng, args.places, DIM)
    queries = place_views(rng, places, rng.integers(0, args.places, args.queries))

    rss_before = _rss_mib()
    vectors = np.empty((n, DIM), np.float32)
    for first in range(0, n, CHUNK):
        m = min(CHUNK, n - first)
        vectors[first : first + m] = place_views(rng, places, rng.integers(0, args.places, m))
    exact = np.argsort(-(queries @ vectors.T), axis=1)[:, :k]
    start = time.perf_counter()
    view = AnnView.build(vectors, AnnOptions(min_references=1))
    build_s = time.perf_counter() - start
    rss_after = _rss_mib()

    with threadpool_limits(1):  # one request searches on one thread (faiss and BLAS)
        sweep = []
        for rerank in args.rerank:
            for nprobe in args.nprobe:
                view.index.options = AnnOptions(min_references=1, nprobe=nprobe, rerank=rerank)
                latencies, hits = [], 0
                for q in range(args.queries):
                    start = time.perf_counter()
                    rows, _ = view.search(queries[q], k, vectors)
                    latencies.append((time.perf_counter() - start) * 1e3)
                    hits += len(set(rows.tolist()) & set(exact[q].tolist()))
                p50, p90 = np.percentile(latencies, [50, 90])
                sweep.append((rerank, nprobe, p50, p90, hits / (k * args.queries)))
        exact_ms = []
        for q in range(min(20, args.queries)):
            start = time.perf_counter()
            np.argpartition(-(vectors @ queries[q]), k)[:k]
            exact_ms.append((time.perf_counter() - start) * 1e3)

    print(f"faiss {faiss.__version__}, IVF-SQ8, nlist {int(np.sqrt(n))}, rescored exactly")
    print(f"references: {n} synthetic unit vectors, {DIM}-D (VLAD, 8 x 128), {args.places} places")
    print(f"build (train + add): {build_s:.1f} s")
    print(f"top-10 over {args.queries} queries, one thread:")
    print("| rerank | nprobe | p50 ms | p90 ms | recall@10 vs exact |")
    print("|---|---|---|---|---|")
    for rerank, nprobe, p50, p90, recall in sweep:
        print(f"| {rerank} | {nprobe} | {p50:.2f} | {p90:.2f} | {recall:.3f} |")
    print(f"exact search (numpy, one thread): p50 {np.median(exact_ms):.0f} ms")
    print(
        f"memory per process: index codes + ids {view.index.nbytes() / 2**20:.0f} MiB, float32 "
        f"matrix {vectors.nbytes / 2**20:.0f} MiB; RSS grew {rss_after - rss_before:.0f} MiB "
        f"(peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB)"
    )


if __name__ == "__main__":
    main()
