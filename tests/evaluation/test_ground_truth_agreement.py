"""``tools/benchmarks/ground_truth``: on a rendered scene, whose poses are exact, the relative
pose from the images agrees with the ground truth's, and a ground truth turned or moved by a
known amount is read as that far off."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from services.features.sift import SiftExtractor
from services.geometry.rigid import Rigid3d
from services.matching.nearest_neighbor import NearestNeighborMatcher
from tools.benchmarks.ground_truth import MIN_INLIERS, FeatureCache, compare, nearest
from tools.evaluation.datasets import PosedImage
from tools.synthetic.scene import SyntheticView, encode_png


def _posed(view: SyntheticView, root: Path) -> PosedImage:
    path = root / view.name
    path.write_bytes(encode_png(view.image))
    return PosedImage(view.name, path, view.camera, view.cam_from_world)


def _turned(image: PosedImage, degrees: float) -> PosedImage:
    """``image`` with its ground-truth camera turned by ``degrees`` about its optical axis."""
    turn = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(degrees)]))[0]
    pose = image.cam_from_world
    return replace(image, cam_from_world=Rigid3d(turn @ pose.rotation, turn @ pose.translation))


def _moved(image: PosedImage, offset: np.ndarray) -> PosedImage:
    """``image`` with its ground-truth camera centre moved by ``offset`` (world frame)."""
    pose = image.cam_from_world
    return replace(
        image, cam_from_world=Rigid3d(pose.rotation, -pose.rotation @ (pose.center + offset))
    )


def test_exact_poses_agree_and_a_turned_or_moved_one_is_read(
    reference_views: list[SyntheticView], tmp_path: Path
) -> None:
    images = [_posed(view, tmp_path) for view in reference_views[:8]]
    query, reference = images[0], nearest(images[0], images[1:], 1)[0]
    features, matcher = FeatureCache(SiftExtractor()), NearestNeighborMatcher(0.8)

    found = compare(query, reference, features, matcher)
    assert found is not None
    inliers, exact, direction = found
    assert inliers >= MIN_INLIERS
    assert exact < 0.1
    assert direction < 0.5

    turned = compare(query, _turned(reference, 3.0), features, matcher)
    assert turned is not None
    assert abs(turned[1] - 3.0) < 0.1

    # across the baseline by its length × tan 10°: the direction of travel turns by 10°
    baseline = reference.cam_from_world.center - query.cam_from_world.center
    across = np.cross(baseline, query.cam_from_world.rotation[2])
    offset = np.linalg.norm(baseline) * np.tan(np.radians(10.0)) * across / np.linalg.norm(across)
    moved = compare(query, _moved(reference, offset), features, matcher)
    assert moved is not None
    assert moved[1] < 0.1
    assert abs(moved[2] - 10.0) < 1.0
