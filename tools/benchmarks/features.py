"""The feature configurations on redkitchen: time per image and pair, and correct matches.

For each preset of ``services/features/configs.py`` whose models are built it prints the median
extraction time per image (at the preset's size), the median time of its matcher on one pair
(a LightGlue preset runs LightGlue on it, on the preset's keypoints), and per frame gap (10,
20, 40) the median matches and correct matches per pair: a match is correct when its symmetric
epipolar distance under the ground-truth poses is below 2 px (fx = fy = 525, cx = 320,
cy = 240). Pairs start at frames 0, 100, …, 900. ``--max-keypoints`` runs every preset at
another keypoint budget. Run from the repository root after ``scripts/build_models.sh``::

    .venv/bin/python -m tools.benchmarks.features [--dataset DIR] [--models-dir models] \
        [--only disk] [--max-keypoints 2048]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from services.components import ModelStore, build_features
from services.features.base import LocalFeatures
from services.features.configs import FEATURE_CONFIGS, FeatureConfig
from services.geometry.epipolar import epipolar_errors
from services.runtime.manifest import read_manifest
from tools.benchmarks.images import load_rgb
from tools.evaluation.datasets import redkitchen_dataset

GAPS = (10, 20, 40)
STARTS = range(0, 1000, 100)
CORRECT_PX = 2.0


def _presets(models: ModelStore, max_keypoints: int | None) -> dict[str, FeatureConfig]:
    """Label → preset, for the presets whose models are built (at ``max_keypoints``)."""
    built = read_manifest(models.models_dir)
    presets = {}
    for config in FEATURE_CONFIGS.values():
        if not set(config.models) <= set(built):
            print(
                f"{config.name}: skipped, needs `slloc models build --models "
                f"{','.join(config.models)}`"
            )
            continue
        if max_keypoints is None:
            presets[config.name] = config
        else:
            label = f"{config.name} at {max_keypoints} keypoints"
            presets[label] = replace(config, max_keypoints=max_keypoints)
    return presets


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    root = Path(__file__).resolve().parents[2]
    parser.add_argument(
        "--dataset", type=Path, default=root / ".." / "shared" / "datasets" / "redkitchen"
    )
    parser.add_argument("--models-dir", type=Path, default=root / "models")
    parser.add_argument("--only", default="", help="run the presets whose name contains this")
    parser.add_argument(
        "--max-keypoints", type=int, help="every preset at this keypoint budget instead of its own"
    )
    args = parser.parse_args()
    images = redkitchen_dataset(args.dataset).images
    frames = sorted({s + g for s in STARTS for g in (0, *GAPS) if s + g < len(images)})
    pixels = {i: load_rgb(images[i].image_path) for i in frames}
    print(f"{len(frames)} frames, {len(STARTS)} pairs per gap; correct = epipolar error < 2 px")
    header = "| preset | extract ms/image | match ms/pair | " + " | ".join(
        f"gap {g}: matches / correct" for g in GAPS
    )
    rows = []
    models = ModelStore(args.models_dir)
    for label, config in _presets(models, args.max_keypoints).items():
        if args.only not in label:
            continue
        extractor, matcher = build_features(config, models)
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
