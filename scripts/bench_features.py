"""Local features and matchers on redkitchen: time per image and pair, and correct matches.

For each combination it prints the median extraction time per image (at the configured size),
the median matching time per pair, and per frame gap (10, 20, 40) the median matches and
correct matches per pair: a match is correct when its symmetric epipolar distance under the
ground-truth poses is below 2 px (fx = fy = 525, cx = 320, cy = 240). Pairs start at frames
0, 100, …, 900. Run from the repository root after ``scripts/build_models.sh``::

    .venv/bin/python scripts/bench_features.py [--dataset DIR] [--models-dir models]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from app.evaluation.datasets import PosedImage, redkitchen_dataset
from services.components import ModelStore
from services.features.aliked_onnx import OnnxAlikedExtractor, ResizeOptions
from services.features.base import FeatureExtractor, LocalFeatures
from services.features.sift import SiftExtractor
from services.geometry.epipolar import epipolar_errors
from services.matching.base import Matcher
from services.matching.lightglue_onnx import OnnxLightGlueMatcher
from services.matching.nearest_neighbor import NearestNeighborMatcher

GAPS = (10, 20, 40)
STARTS = range(0, 1000, 100)
CORRECT_PX = 2.0


def _combinations(models: ModelStore) -> dict[str, Callable[[], tuple[FeatureExtractor, Matcher]]]:
    def aliked(keypoints: int, lightglue: bool) -> tuple[FeatureExtractor, Matcher]:
        budget = models.entry("aliked-n16").keypoint_budget or keypoints
        extractor = OnnxAlikedExtractor(
            models.session("aliked-n16"), "aliked-n16", budget, ResizeOptions(keypoints, 640)
        )
        matcher: Matcher = (
            OnnxLightGlueMatcher(models.session("lightglue-aliked"), "lightglue-aliked")
            if lightglue
            else NearestNeighborMatcher(ratio=0.95)
        )
        return extractor, matcher

    return {
        "sift + mnn (fallback)": lambda: (SiftExtractor(), NearestNeighborMatcher()),
        "aliked-n16 1024 + mnn": lambda: aliked(1024, False),
        "aliked-n16 1024 + lightglue": lambda: aliked(1024, True),
        "aliked-n16 2048 + lightglue": lambda: aliked(2048, True),
    }


def _load(image: PosedImage) -> np.ndarray:
    return np.ascontiguousarray(cv2.imread(str(image.image_path))[:, :, ::-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    root = Path(__file__).resolve().parents[1]
    parser.add_argument(
        "--dataset", type=Path, default=root / ".." / "shared" / "datasets" / "redkitchen"
    )
    parser.add_argument("--models-dir", type=Path, default=root / "models")
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
