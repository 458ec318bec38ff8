"""The votes of a capture's frames on the references that cover them, on exact geometry."""

from __future__ import annotations

import numpy as np

from services.capture.freshness import Vote, agreeing_matches, covering, stale_references
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d

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
