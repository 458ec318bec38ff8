"""The votes of a capture's frames on the references that cover them, on exact geometry."""

from __future__ import annotations

import numpy as np

from services.capture.freshness import (
    Vote,
    agreeing_matches,
    covering,
    frame_votes,
    reusable_inliers,
    stale_references,
)
from services.features.base import LocalFeatures
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.localization.answer import LocalizationResult, RetrievedReference
from services.matching.nearest_neighbor import NearestNeighborMatcher
from services.references.store import ReferenceView

CAMERA = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))


def _looking_along_z(x: float, yaw_deg: float = 0.0) -> Rigid3d:
    yaw = np.radians(yaw_deg)
    rotation = np.array([[np.cos(yaw), 0, -np.sin(yaw)], [0, 1, 0], [np.sin(yaw), 0, np.cos(yaw)]])
    return Rigid3d(rotation, -rotation @ np.array([x, 0.0, 0.0]))


def _project(pose: Rigid3d, points: np.ndarray) -> np.ndarray:
    cam = pose.apply(points)
    return cam[:, :2] / cam[:, 2:] * 500.0 + [320.0, 240.0]


def test_the_nearest_references_looking_the_same_way_cover_a_frame() -> None:
    references = [
        _looking_along_z(0.1),
        _looking_along_z(3.0),  # too far
        _looking_along_z(0.2, 60.0),  # turned away
        _looking_along_z(-0.05),
    ]
    assert covering(_looking_along_z(0.0), references, spacing=0.5) == [3, 0]


def test_matches_that_fit_the_two_poses_are_counted() -> None:
    rng = np.random.default_rng(1)
    points = rng.uniform([-2, -1, 4], [2, 1, 8], size=(200, 3))
    frame, reference = _looking_along_z(0.0), _looking_along_z(0.3)
    xy_frame, xy_reference = _project(frame, points), _project(reference, points)
    matches = np.stack([np.arange(200), np.arange(200)], axis=1)
    # 150 true matches, 50 shuffled among themselves
    matches[150:, 1] = rng.permutation(matches[150:, 1])
    counted = agreeing_matches(CAMERA, frame, xy_frame, CAMERA, reference, xy_reference, matches)
    assert 150 <= counted < 160  # a shuffled match may fall near its epipolar line by chance


def test_a_reference_is_stale_when_every_vote_on_it_is() -> None:
    votes = [
        Vote("a", "f1", 3, 400),
        Vote("a", "f2", 9, 300),
        Vote("b", "f1", 5, 400),
        Vote("b", "f2", 120, 300),  # one frame still matches it
        Vote("c", "f1", 14, 100),  # under 15 but not under a tenth of 100
    ]
    verdicts = stale_references(votes)
    assert [v.frame for v in verdicts["a"]] == ["f1", "f2"]
    assert verdicts["b"] == [] and verdicts["c"] == []


def _features(pose: Rigid3d, points: np.ndarray, descriptors: np.ndarray) -> LocalFeatures:
    xy = _project(pose, points).astype(np.float32)
    return LocalFeatures(xy, descriptors, np.ones(len(points), np.float32), (640, 480))


def _localization(retrieved: list[RetrievedReference], camera: Camera) -> LocalizationResult:
    return LocalizationResult(
        localized=True,
        reason=None,
        estimator="auto",
        cam_from_world=_looking_along_z(0.0),
        num_inliers=sum(r.num_inliers for r in retrieved),
        confidence=0.99,
        retrieved=retrieved,
        timings_ms={},
        stats={},
        camera=camera,
    )


def test_a_frame_votes_from_its_localization_and_matches_only_to_confirm_a_stale_vote() -> None:
    rng = np.random.default_rng(2)
    points = rng.uniform([-2, -1, 4], [2, 1, 8], size=(300, 3))
    descriptors = rng.normal(size=(300, 32)).astype(np.float32)
    descriptors /= np.linalg.norm(descriptors, axis=1, keepdims=True)
    frame = _looking_along_z(0.0)
    kept, swapped = _looking_along_z(0.2), _looking_along_z(-0.2)
    references = [
        ReferenceView("kept", "kept", CAMERA, kept, _features(kept, points, descriptors), None),
        # another place seen from its pose: what looks alike lies elsewhere
        ReferenceView(
            "swapped",
            "swapped",
            CAMERA,
            swapped,
            _features(swapped, points[rng.permutation(300)], descriptors),
            None,
        ),
    ]
    # the localization's inliers: 200 with the kept reference; 3 stray ones with the swapped
    # one, too few to vote fresh
    retrieved = [
        RetrievedReference(
            "kept",
            "kept",
            0.9,
            250,
            200,
            _project(frame, points[:200]),
            _project(kept, points[:200]),
        ),
        RetrievedReference(
            "swapped",
            "swapped",
            0.5,
            40,
            3,
            _project(frame, points[:3]),
            _project(swapped, points[3:6]),
        ),
    ]
    described: list[LocalFeatures] = []

    def describe() -> LocalFeatures:
        described.append(_features(frame, points, descriptors))
        return described[-1]

    inliers = reusable_inliers(_localization(retrieved, CAMERA), CAMERA)
    votes = frame_votes(
        "f", CAMERA, frame, references, inliers, describe, NearestNeighborMatcher(), 200
    )
    assert [(v.image_id, v.stale) for v in votes] == [("kept", False), ("swapped", True)]
    assert votes[0].inliers == 200  # from the localization, with nothing matched
    assert votes[1].inliers < 15 and len(described) == 1  # matched in full to confirm it
    # localized with another camera, its inliers are not the frame's pixels: none reused
    other = Camera("PINHOLE", 640, 480, (520.0, 520.0, 320.0, 240.0))
    assert reusable_inliers(_localization(retrieved, other), CAMERA) == {}
