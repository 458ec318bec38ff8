"""Median run time and accuracy of every registered estimator on synthetic correspondences:
top-10 references, ~1000 matches per pair (1 px noise, 30 % outliers, metric depth).

Usage: python -m tools.benchmarks.estimators [--runs 3] [--matches 1000]
       [--min-iterations 1000] [NAME ...]
For comparison, the CPU times per query in Panek et al. 2025, "A Guide to Structureless Visual
Localization": E5+1 265 ms, LazyLoc 101 ms, Ess. mat. 1623 ms, local triangulation all 2909 ms /
pairs 1528 ms.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from services.estimators.options import EstimatorOptions, RansacOptions
from services.estimators.registry import estimator_names, get_estimator
from services.geometry.rigid import pose_error
from tools.synthetic.correspondences import make_correspondences

# CPU time per query (ms) in Panek et al. 2025 for the estimator of each family
PAPER_MS = {
    "e5p1": 265.0,
    "motion_averaging": 101.0,
    "essential_5pt": 1623.0,
    "local_tri_all": 2909.0,
    "local_tri_pairs": 1528.0,
}


def med(values: list[float]) -> float:
    return float(np.median(values)) if values else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", default=estimator_names())
    parser.add_argument("--runs", type=int, default=3, help="scenes (seeds) per estimator")
    parser.add_argument("--matches", type=int, default=1000, help="matches per reference")
    parser.add_argument("--references", type=int, default=10)
    parser.add_argument("--min-iterations", type=int, default=RansacOptions().min_iterations)
    args = parser.parse_args()
    scenes = [
        make_correspondences(
            seed=seed,
            num_references=args.references,
            matches_per_reference=args.matches,
            with_depth=True,
        )
        for seed in range(args.runs)
    ]
    options = EstimatorOptions(ransac=RansacOptions(min_iterations=args.min_iterations))
    print(
        f"{'estimator':<22}{'median ms':>10}{'paper ms':>10}{'speed-up':>10}"
        f"{'pos err %':>11}{'rot err °':>11}  failures"
    )
    for name in args.names:
        estimator = get_estimator(name)
        times: list[float] = []
        pos: list[float] = []
        rot: list[float] = []
        failures: list[str] = []
        for scene in scenes:
            start = time.perf_counter()
            result = estimator.estimate(scene.query_camera, scene.references, options)
            times.append((time.perf_counter() - start) * 1000.0)
            if result.cam_from_world is None:
                failures.append(str(result.failure_reason))
                continue
            p, r = pose_error(result.cam_from_world, scene.query_pose)
            pos.append(100.0 * p / scene.scene_depth)
            rot.append(r)
        paper = PAPER_MS.get(name)
        speedup = f"{paper / med(times):.1f}×" if paper else "-"
        print(
            f"{name:<22}{med(times):>10.0f}{paper or float('nan'):>10.0f}{speedup:>10}"
            f"{med(pos):>11.3f}{med(rot):>11.3f}  {', '.join(failures) or '-'}"
        )


if __name__ == "__main__":
    main()
