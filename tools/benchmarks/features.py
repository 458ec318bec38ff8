"""Local features and matchers on redkitchen: time per image and pair, and correct matches.

For each combination it prints the median extraction time per image (at the configured size),
the median matching time per pair, and per frame gap (10, 20, 40) the median matches and
correct matches per pair: a match is correct when its symmetric epipolar distance under the
ground-truth poses is below 2 px (fx = fy = 525, cx = 320, cy = 240). Pairs start at frames
0, 100, …, 900. DISK rows appear when DISK is built (``slloc models build --models
disk,lightglue-disk``). Run from the repository root after ``scripts/build_models.sh``::

    .venv/bin/python -m tools.benchmarks.features [--dataset DIR] [--models-dir models] \
        [--only disk]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from services.components import ModelStore
from services.features.base import FeatureExtractor, LocalFeatures
from services.features.keypoint_onnx import OnnxKeypointExtractor, ResizeOptions
from services.features.sift import SiftExtractor
from services.geometry.epipolar import epipolar_errors
from services.matching.base import Matcher
from services.matching.lightglue_onnx import OnnxLightGlueMatcher
from services.matching.nearest_neighbor import NearestNeighborMatcher
from services.runtime.manifest import read_manifest
from tools.evaluation.datasets import PosedImage, redkitchen_dataset

GAPS = (10, 20, 40)
STARTS = range(0, 1000, 100)
CORRECT_PX = 2.0


def _combinations(models: ModelStore) -> dict[str, Callable[[], tuple[FeatureExtractor, Matcher]]]:
    def learned(model: str, keypoints: int, lightglue: bool) -> tuple[FeatureExtractor, Matcher]:
        entry = models.entry(model)
        extractor = OnnxKeypointExtractor(
            models.session(model),
            model,
            entry.keypoint_budget or keypoints,
            ResizeOptions(keypoints, 640),
        )
        matcher_name = str(entry.config["matcher"])
        matcher: Matcher = (
            OnnxLightGlueMatcher(models.session(matcher_name), matcher_name)
            if lightglue
            else NearestNeighborMatcher(ratio=0.95)
        )
        return extractor, matcher

    combinations: dict[str, Callable[[], tuple[FeatureExtractor, Matcher]]] = {
        "sift + mnn (fallback)": lambda: (SiftExtractor(), NearestNeighborMatcher()),
    }
    built = read_manifest(models.models_dir)
    for model in ("aliked-n16", "disk"):  # DISK only when built (`--models disk,lightglue-disk`)
        if model not in built:
            continue
        combinations |= {
            f"{model} 1024 + mnn": partial(learned, model, 1024, False),
            f"{model} 1024 + lightglue": partial(learned, model, 1024, True),
            f"{model} 2048 + lightglue": partial(learned, model, 2048, True),
        }
    return combinations


def _load(image: PosedImage) -> np.ndarray:
    bgr = cv2.imread(str(image.image_path))
    if bgr is None:
        raise OSError(f"cannot read {image.image_path}")
    return np.ascontiguousarray(bgr[:, :, ::-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    root = Path(__file__).resolve().parents[2]
    parser.add_argument(
        "--dataset", type=Path, default=root / ".." / "shared" / "datasets" / "redkitchen"
    )
    parser.add_argument("--models-dir", type=Path, default=root / "models")
    parser.add_argument("--only", default="", help="run the rows whose label contains this")
    args = parser.parse_args()
    images = redkitchen_dataset(args.dataset).images
    frames = sorted({s + g for s in STARTS for g in (0, *GAPS) if s + g < len(images)})
    pixels = {i: _load(images[i]) for i in frames}
    print(f"{len(frames)} frames, {len(STARTS)} pairs per gap; correct = epipolar error < 2 px")
    header = "| features + matcher | extract ms/image | match ms/pair | " + " | ".join(
        f"gap {g}: matches / correct" for g in GAPS
    )
    rows = []
    for label, make in _combinations(ModelStore(args.models_dir)).items():
        if args.only not in label:
            continue
        extractor, matcher = make()
        features: dict[int, LocalFeatures] = {}
        extract_ms = []
        for i in frames:
            start = time.perf_counter()
            features[i] = extractor.extract(pixels[i])
            extract_ms.append((time.perf_counter() - start) * 1000)
        match_ms, cells = [], []
        for gap in GAPS:
            counts, correct = [], []
            for s in STARTS:
                if s + gap >= len(images):
                    continue
                a, b = images[s], images[s + gap]
                start = time.perf_counter()
                pairs = matcher.match(features[s], features[s + gap])
                match_ms.append((time.perf_counter() - start) * 1000)
                errors = epipolar_errors(
                    a.camera,
                    a.cam_from_world,
                    features[s].keypoints[pairs[:, 0]].astype(np.float64),
                    b.camera,
                    b.cam_from_world,
                    features[s + gap].keypoints[pairs[:, 1]].astype(np.float64),
                )
                counts.append(len(pairs))
                correct.append(int((errors < CORRECT_PX).sum()))
            cells.append(f"{np.median(counts):.0f} / {np.median(correct):.0f}")
        rows.append(
            f"| {label} | {np.median(extract_ms):.0f} | {np.median(match_ms):.0f} | "
            + " | ".join(cells)
            + " |"
        )
        print(rows[-1], flush=True)
    print()
    print(header + " |")
    print("|---" * (3 + len(GAPS)) + "|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
