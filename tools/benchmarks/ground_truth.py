"""How far a dataset's ground truth agrees with its images.

For each query of a split and each of its nearest references by ground truth, the relative
pose estimated from the two images (a feature configuration's matches, PoseLib's relative
pose with the dataset's intrinsics) is compared with the one the ground-truth poses give: the
angle between the two rotations, and the angle between the two directions of travel (the
baseline's direction, which the images fix up to scale; read only for pairs at least
``MIN_BASELINE_M`` apart). An evaluation cannot score answers more finely than this
disagreement: an estimator that agrees with the images is counted that far off. A position
error ``e`` across a baseline ``b`` turns the direction by about ``atan(e / b)``.

Prints each query's pairs, then the median / p90 disagreements over all pairs, and for pairs
whose frames are near in the sequence (index gap ≤ ``--near-gap``) and far apart.

Each pair prints as ``rotation / direction disagreement (inliers, turn, baseline)``.

Run from the repository root:
``.venv/bin/python -m tools.benchmarks.ground_truth [DATASET] [--references RULE]
[--queries RULE] [--features aliked-full] [--pairs 3]``
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import poselib

from services.components import ModelStore, build_features
from services.features.base import FeatureExtractor, LocalFeatures
from services.features.configs import get_feature_config
from services.geometry.rigid import Rigid3d, rotation_error_deg
from services.matching.base import Matcher
from tools.benchmarks.images import load_rgb
from tools.evaluation.datasets import PosedImage, open_dataset
from tools.evaluation.split import split_dataset

REDKITCHEN = Path("../shared/datasets/redkitchen")
MIN_INLIERS = 100  # fewer: the image-based rotation is too loose to judge the ground truth by
MIN_BASELINE_M = 0.1  # shorter: the direction of travel is too loose to judge
METRES_PER_RADIAN = 0.5  # nearest references: centre distance plus this per radian of turn


@dataclass(frozen=True)
class Pair:
    query: int  # dataset indices
    reference: int
    turn_deg: float  # the ground truth's relative rotation
    baseline_m: float  # the ground truth's distance between the two centres
    inliers: int
    disagreement_deg: float  # image-based relative rotation against the ground truth's
    direction_deg: float  # the same for the direction of travel; nan below MIN_BASELINE_M


def nearest(query: PosedImage, references: list[PosedImage], k: int) -> list[PosedImage]:
    def cost(reference: PosedImage) -> float:
        a, b = reference.cam_from_world, query.cam_from_world
        distance = np.linalg.norm(a.center - b.center)
        turn = np.radians(rotation_error_deg(a.rotation, b.rotation))
        return float(distance + METRES_PER_RADIAN * turn)

    return sorted(references, key=cost)[:k]


def _camera(image: PosedImage) -> dict[str, object]:
    cam = image.camera
    return {"model": cam.model, "width": cam.width, "height": cam.height, "params": [*cam.params]}


def _relative(a: PosedImage, b: PosedImage) -> Rigid3d:
    """b's camera from a's camera, by the ground truth."""
    return b.cam_from_world.compose(a.cam_from_world.inverse())


class FeatureCache:
    """The features of each image, extracted once."""

    def __init__(self, extractor: FeatureExtractor) -> None:
        self.extractor = extractor
        self.cache: dict[Path, LocalFeatures] = {}

    def __call__(self, image: PosedImage) -> LocalFeatures:
        if image.image_path not in self.cache:
            self.cache[image.image_path] = self.extractor.extract(load_rgb(image.image_path))
        return self.cache[image.image_path]


def compare(
    query: PosedImage, reference: PosedImage, features: FeatureCache, matcher: Matcher
) -> tuple[int, float, float] | None:
    """Inliers and the disagreements (°) of the image-based relative rotation and direction of
    travel with the ground truth's (the direction nan below ``MIN_BASELINE_M``), or None below
    ``MIN_INLIERS``."""
    q, r = features(query), features(reference)
    matches = matcher.match(q, r)
    if len(matches) < MIN_INLIERS:
        return None
    pose, info = poselib.estimate_relative_pose(
        q.keypoints[matches[:, 0]].astype(np.float64),
        r.keypoints[matches[:, 1]].astype(np.float64),
        _camera(query),
        _camera(reference),
        {"max_epipolar_error": 1.0},
        {},
    )
    if info["num_inliers"] < MIN_INLIERS:
        return None
    truth = _relative(query, reference)
    direction = float("nan")
    if np.linalg.norm(truth.translation) >= MIN_BASELINE_M:
        cosine = np.dot(pose.t, truth.translation) / (
            np.linalg.norm(pose.t) * np.linalg.norm(truth.translation)
        )
        direction = float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))
    return int(info["num_inliers"]), rotation_error_deg(pose.R, truth.rotation), direction


def _summary(label: str, pairs: list[Pair]) -> str:
    if not pairs:
        return f"{label}: no pairs"
    values = np.array([p.disagreement_deg for p in pairs])
    turns = np.array([p.turn_deg for p in pairs])
    text = (
        f"{label}: {len(pairs)} pairs (ground-truth turn median {np.median(turns):.0f}°), "
        f"rotation disagreement median {np.median(values):.2f}°, "
        f"p90 {np.percentile(values, 90):.2f}°, max {values.max():.2f}°"
    )
    judged = [p for p in pairs if not np.isnan(p.direction_deg)]
    if judged:
        directions = np.array([p.direction_deg for p in judged])
        baselines = np.array([p.baseline_m for p in judged])
        text += (
            f"; direction of travel ({len(judged)} pairs, baseline median "
            f"{np.median(baselines):.2f} m) median {np.median(directions):.2f}°, "
            f"p90 {np.percentile(directions, 90):.2f}°, max {directions.max():.2f}°"
        )
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path, nargs="?", default=REDKITCHEN)
    parser.add_argument("--references", help="split rule (default: the dataset's suggestion)")
    parser.add_argument("--queries", help="split rule (default: the dataset's suggestion)")
    parser.add_argument("--features", default="aliked-full", help="a feature configuration")
    parser.add_argument("--models-dir", type=Path, default=Path("models"))
    parser.add_argument("--pairs", type=int, default=3, help="nearest references per query")
    parser.add_argument("--near-gap", type=int, default=100, help="frames apart to count as near")
    args = parser.parse_args()

    dataset = open_dataset(args.dataset)
    split = split_dataset(dataset, args.references, args.queries)
    index = {image.name: i for i, image in enumerate(dataset.images)}
    extractor, matcher = build_features(
        get_feature_config(args.features), ModelStore(args.models_dir)
    )
    features = FeatureCache(extractor)
    pairs: list[Pair] = []
    for query in split.queries:
        line = []
        for reference in nearest(query, split.references, args.pairs):
            found = compare(query, reference, features, matcher)
            if found is None:
                continue
            relative = _relative(query, reference)
            turn = rotation_error_deg(relative.rotation, np.eye(3))
            baseline = float(np.linalg.norm(relative.translation))
            pair = Pair(index[query.name], index[reference.name], turn, baseline, *found)
            pairs.append(pair)
            line.append(
                f"{reference.name} {pair.disagreement_deg:.2f}° / {pair.direction_deg:.1f}° "
                f"({pair.inliers} inliers, turn {turn:.0f}°, {baseline:.2f} m)"
            )
        print(f"{query.name}: " + (" | ".join(line) or "no pair"), flush=True)
    near = [p for p in pairs if abs(p.query - p.reference) <= args.near_gap]
    far = [p for p in pairs if abs(p.query - p.reference) > args.near_gap]
    print(_summary("all", pairs))
    print(_summary(f"frames ≤ {args.near_gap} apart", near))
    print(_summary(f"frames > {args.near_gap} apart", far))


if __name__ == "__main__":
    main()
