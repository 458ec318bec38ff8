"""Wall time of every path of a localization under one time budget (default 1 s), on the
problems of ``tests/engine/test_time_budget.py``: every registered estimator (with the
request's camera), the focal estimation of a query without one, the joint estimate of two
frames (``rig_pose``) on 100 references × 1000 matches; and the localizer's single frame with
and without a camera, the turn search and three frames on a 96-reference map at top-k 50.

Prints per path the median and the largest wall time over ``--runs`` runs, the answer
(``time_budget_exceeded`` or localized) and the system load (``uptime``) before and after:
figures taken on a loaded machine are inflated.

Usage: python -m tools.benchmarks.time_budget [--budget 1.0] [--runs 3] [PATH ...]
"""

from __future__ import annotations

import argparse
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from services.components import EngineConfig, build_localizer
from services.estimators.options import EstimatorOptions
from services.estimators.registry import estimator_names
from services.estimators.rig_pose import RigFrame, estimate_rig_pose
from services.localization.frames import QueryFrame, localize_frames
from services.localization.localizer import LocalizeParams
from tools.synthetic.budget import TOP_K, answer_in_budget, copied_store, large_correspondences
from tools.synthetic.scene import SyntheticScene, encode_png

# a path: run once at a budget (seconds), answer what came out
Path_ = Callable[[float], str]


def estimator_paths() -> dict[str, Path_]:
    large = large_correspondences()

    def answer(name: str, focal_estimated: bool) -> Path_:
        def run(budget: float) -> str:
            result = answer_in_budget(name, large, focal_estimated, budget)
            return "localized" if result.failure_reason is None else str(result.failure_reason)

        return run

    def rig(budget: float) -> str:
        frames = [
            RigFrame(large.query_camera, large.query_pose, large.references),
            RigFrame(large.query_camera, large.query_pose, large.references[::-1]),
        ]
        found = estimate_rig_pose(frames, EstimatorOptions(time_budget_s=budget))
        return "localized" if found.failure_reason is None else str(found.failure_reason)

    paths = {name: answer(name, False) for name in estimator_names()}
    paths["focal (no camera)"] = answer("e5p1", True)
    paths["rig (2 frames)"] = rig
    return paths


def localizer_paths() -> dict[str, Path_]:
    localizer = build_localizer(
        EngineConfig.resolve(Path("/nonexistent-models"), max_pixels=40_000_000)
    )
    scene = SyntheticScene(seed=0)
    store = copied_store(localizer, scene.views(24, stream=1, prefix="ref"))
    queries = scene.views(10, stream=2, prefix="query")

    def single(with_camera: bool, turned: bool = False) -> Path_:
        view = queries[1 if turned else 0]
        image = np.ascontiguousarray(np.rot90(view.image)) if turned else view.image
        encoded = encode_png(image)

        def run(budget: float) -> str:
            camera = view.camera if with_camera and not turned else None
            params = LocalizeParams(camera=camera, top_k=TOP_K, time_budget_s=budget)
            result = localizer.localize(encoded, params, store)
            return "localized" if result.localized else str(result.reason)

        return run

    frames = [
        QueryFrame(encode_png(view.image), view.camera, view.cam_from_world) for view in queries[:3]
    ]

    def several(budget: float) -> str:
        params = LocalizeParams(top_k=TOP_K, time_budget_s=budget)
        answer = localize_frames(localizer, frames, params, store)
        return "localized" if answer.map_from_session is not None else str(answer.result.reason)

    return {
        "localize camera": single(True),
        "localize no-camera": single(False),
        "localize turn search": single(False, turned=True),
        "localize 3 frames": several,
    }


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="*", help="paths to run (default: all)")
    parser.add_argument("--budget", type=float, default=1.0, help="time budget, seconds")
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    paths = {**estimator_paths(), **localizer_paths()}
    chosen = args.paths or list(paths)
    print(f"budget {args.budget:.2f} s, {args.runs} runs; load before: {uptime()}")
    print(f"{'path':<24}{'median s':>10}{'max s':>8}{'over s':>8}  answers")
    for name in chosen:
        times: list[float] = []
        answers: set[str] = set()
        for _ in range(args.runs):
            start = time.perf_counter()
            answers.add(paths[name](args.budget))
            times.append(time.perf_counter() - start)
        worst = max(times)
        print(
            f"{name:<24}{float(np.median(times)):>10.3f}{worst:>8.3f}"
            f"{worst - args.budget:>8.3f}  {', '.join(sorted(answers))}",
            flush=True,
        )
    print(f"load after: {uptime()}")


if __name__ == "__main__":
    main()
