"""Aligning a capture session to a map, and correcting its drift, on synthetic trajectories with
exact ground truth."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from services.capture.alignment import (
    CheckedFrame,
    Similarity,
    align,
    check_indices,
    densify,
    path_length,
    tolerance_m,
)
from services.capture.drift import anchored, corrected_poses, slerp
from services.capture.spacing import map_spacing, new_views
from services.geometry.rigid import (
    Rigid3d,
    matrix_to_quaternion,
    quaternion_to_matrix,
    rotation_error_deg,
)


def _rotation(rng: np.random.Generator, degrees: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    half = np.radians(degrees) / 2
    return quaternion_to_matrix(np.array([np.cos(half), *(np.sin(half) * axis)]))


def _session(rng: np.random.Generator, count: int = 40, step_m: float = 0.1) -> list[Rigid3d]:
    """A walk of ``count`` cameras, each looking ahead with some wobble."""
    poses = []
    center = np.zeros(3)
    for i in range(count):
        center = center + np.array([step_m, 0.02 * np.sin(i / 3), 0.01 * np.cos(i / 5)])
        rotation = _rotation(rng, 10.0)
        poses.append(Rigid3d(rotation, -rotation @ center))
    return poses


def _truth(rng: np.random.Generator, scale: float = 1.0) -> Similarity:
    return Similarity(_rotation(rng, 70.0), rng.normal(size=3) * 5, scale)


def _checked(
    session: list[Rigid3d],
    truth: Similarity,
    rng: np.random.Generator,
    noise_m: float = 0.005,
    noise_deg: float = 0.2,
) -> list[CheckedFrame]:
    frames = []
    for index in check_indices(len(session), 12):
        exact = truth.cam_from_map(session[index])
        rotation = _rotation(rng, noise_deg) @ exact.rotation
        center = exact.center + rng.normal(size=3) * noise_m / np.sqrt(3)
        frames.append(
            CheckedFrame(index, session[index], Rigid3d(rotation, -rotation @ center), 0.9)
        )
    return frames


def _drifted(session: list[Rigid3d], sideways: float, yaw_deg_per_m: float) -> list[Rigid3d]:
    """The session as a drifting tracker reports it: after s metres, its frame has turned
    ``yaw_deg_per_m`` × s degrees about the vertical through the start and moved
    ``sideways`` × s along y."""
    out = []
    travelled = 0.0
    start = session[0].center
    for i, pose in enumerate(session):
        if i:
            travelled += float(np.linalg.norm(pose.center - session[i - 1].center))
        yaw = np.radians(yaw_deg_per_m * travelled)
        turn = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        center = turn @ (pose.center - start) + start + np.array([0.0, sideways * travelled, 0.0])
        rotation = pose.rotation @ turn.T
        out.append(Rigid3d(rotation, -rotation @ center))
    return out


def _error(estimate: Similarity, truth: Similarity, session: list[Rigid3d]) -> float:
    return max(
        float(np.linalg.norm(estimate.cam_from_map(p).center - truth.cam_from_map(p).center))
        for p in session
    )


def test_check_indices_spread_over_the_session_ends_included() -> None:
    assert check_indices(5, 12) == [0, 1, 2, 3, 4]
    picked = check_indices(250, 12)
    assert picked[0] == 0 and picked[-1] == 249 and len(picked) == 12
    assert np.all(np.diff(picked) >= 20)


@pytest.mark.parametrize("metric", [True, False])
def test_alignment_recovers_the_transform(metric: bool) -> None:
    rng = np.random.default_rng(3)
    session = _session(rng)
    truth = _truth(rng, 1.0 if metric else 0.37)
    frames = _checked(session, truth, rng)
    alignment = align(frames, path_length(session), metric)
    assert alignment.reason is None and alignment.map_from_session is not None
    assert alignment.agreeing == len(frames)
    # 12 frames of 5 mm noise: the whole path within 1 cm, the scale within half a per cent
    assert _error(alignment.map_from_session, truth, session) < 0.01
    assert rotation_error_deg(alignment.map_from_session.rotation, truth.rotation) < 0.2
    assert alignment.map_from_session.scale == pytest.approx(truth.scale, rel=5e-3)
    assert alignment.rms_position_m is not None and 0.001 < alignment.rms_position_m < 0.01


def test_similarity_agrees_with_pycolmap_on_exact_centres() -> None:
    rng = np.random.default_rng(4)
    session = _session(rng)
    truth = _truth(rng, 2.5)
    frames = _checked(session, truth, rng, noise_m=0.0, noise_deg=0.0)
    ours = align(frames, path_length(session), metric=False).map_from_session
    assert ours is not None
    src = np.array([f.cam_from_session.center for f in frames])
    dst = np.array([f.cam_from_map.center for f in frames if f.cam_from_map is not None])
    theirs = pycolmap.estimate_sim3d(src, dst)
    assert theirs is not None
    np.testing.assert_allclose(ours.scale, theirs.scale, rtol=1e-9)
    np.testing.assert_allclose(ours.rotation, theirs.rotation.matrix(), atol=1e-9)
    np.testing.assert_allclose(ours.translation, theirs.translation, atol=1e-9)


def test_wrong_localizations_are_outvoted() -> None:
    rng = np.random.default_rng(5)
    session = _session(rng)
    truth = _truth(rng)
    frames = _checked(session, truth, rng)
    for k in (2, 7):  # two confident answers metres off
        bad = frames[k].cam_from_map
        assert bad is not None
        frames[k] = CheckedFrame(
            frames[k].index,
            frames[k].cam_from_session,
            Rigid3d(bad.rotation, bad.translation + 3.0),
            0.9,
        )
    alignment = align(frames, path_length(session), metric=True)
    assert alignment.map_from_session is not None
    assert alignment.agreeing == len(frames) - 2
    assert sorted(r.index for r in alignment.residuals if not r.agrees) == [
        frames[2].index,
        frames[7].index,
    ]
    assert _error(alignment.map_from_session, truth, session) < 0.01


def test_drift_beyond_the_bound_is_refused() -> None:
    rng = np.random.default_rng(6)
    session = _session(rng)
    truth = _truth(rng)
    length = path_length(session)
    # the tracking drifts by 10 % of the distance travelled, ten times the bound
    drifted = _drifted(session, sideways=0.1, yaw_deg_per_m=0.0)
    frames = [
        CheckedFrame(f.index, drifted[f.index], f.cam_from_map, f.confidence)
        for f in _checked(session, truth, rng)
    ]
    alignment = align(frames, length, metric=True)
    assert alignment.map_from_session is None
    assert alignment.reason is not None and "drifted" in alignment.reason
    assert tolerance_m(length) == pytest.approx(0.05)


def test_a_metric_session_at_the_wrong_scale_is_refused() -> None:
    rng = np.random.default_rng(7)
    session = _session(rng)
    truth = _truth(rng, 1.5)  # the session is in other units than the map
    frames = _checked(session, truth, rng)
    assert align(frames, path_length(session), metric=True).map_from_session is None
    assert align(frames, path_length(session), metric=False).map_from_session is not None


def test_too_few_confident_frames_are_refused() -> None:
    rng = np.random.default_rng(8)
    session = _session(rng)
    frames = _checked(session, _truth(rng), rng)
    weak = [
        CheckedFrame(f.index, f.cam_from_session, f.cam_from_map if k < 2 else None, 0.9)
        for k, f in enumerate(frames)
    ]
    alignment = align(weak, path_length(session), metric=True)
    assert alignment.map_from_session is None and alignment.confident == 2
    assert alignment.reason is not None and "too few frames" in alignment.reason


def test_an_unknown_scale_needs_a_long_enough_path() -> None:
    rng = np.random.default_rng(9)
    session = _session(rng, count=40, step_m=0.005)  # 20 cm in all
    frames = _checked(session, _truth(rng, 0.8), rng)
    alignment = align(frames, path_length(session), metric=False)
    assert alignment.map_from_session is None
    assert alignment.reason is not None and "scale is not determined" in alignment.reason


def test_drift_between_anchors_is_corrected() -> None:
    rng = np.random.default_rng(10)
    session = _session(rng, count=60)
    truth = _truth(rng)
    length = path_length(session)
    # the tracking drifts as it goes: after s metres, its frame has turned 0.2° per metre
    # about the vertical through the start and moved 1 % of s sideways
    drifted = _drifted(session, sideways=0.01, yaw_deg_per_m=0.2)
    frames = [
        CheckedFrame(f.index, drifted[f.index], f.cam_from_map, f.confidence)
        for f in _checked(session, truth, rng, noise_m=0.002, noise_deg=0.05)
    ]
    alignment = align(frames, length, metric=True)
    assert alignment.map_from_session is not None
    anchors = {
        r.index: f.cam_from_map
        for r, f in zip(alignment.residuals, frames, strict=True)
        if r.agrees and f.cam_from_map is not None
    }
    placed, shifts = corrected_poses(alignment.map_from_session, drifted, anchors)
    rigid = [alignment.map_from_session.cam_from_map(p) for p in drifted]
    exact = [truth.cam_from_map(p) for p in session]

    def worst(poses: list[Rigid3d]) -> tuple[float, float]:
        return (
            max(
                float(np.linalg.norm(p.center - e.center))
                for p, e in zip(poses, exact, strict=True)
            ),
            max(
                rotation_error_deg(p.rotation, e.rotation)
                for p, e in zip(poses, exact, strict=True)
            ),
        )

    # one transform leaves centimetres and degrees; corrected, every frame is within the
    # anchors' noise plus what drifts between two of them
    assert worst(rigid)[0] > 0.02 and worst(rigid)[1] > 0.4
    assert worst(placed)[0] < 0.006 and worst(placed)[1] < 0.15
    assert len(shifts) == len(anchors) and shifts.max() > 0.01
    # at an anchor the answer is the anchor's own pose
    k = min(anchors)
    np.testing.assert_allclose(placed[k].center, anchors[k].center, atol=1e-9)


def test_slerp_meets_its_ends_and_halves_the_angle() -> None:
    rng = np.random.default_rng(11)
    a, b = _rotation(rng, 30.0), _rotation(rng, 30.0)
    qa, qb = matrix_to_quaternion(a), matrix_to_quaternion(b)
    np.testing.assert_allclose(quaternion_to_matrix(slerp(qa, qb, 0.0)), a, atol=1e-12)
    np.testing.assert_allclose(quaternion_to_matrix(slerp(qa, -qb, 1.0)), b, atol=1e-12)
    half = quaternion_to_matrix(slerp(qa, qb, 0.5))
    assert rotation_error_deg(half, a) == pytest.approx(rotation_error_deg(a, b) / 2, abs=1e-9)
    assert rotation_error_deg(half, b) == pytest.approx(rotation_error_deg(a, b) / 2, abs=1e-9)


def test_a_session_that_overlaps_the_map_briefly_is_checked_densely_there() -> None:
    checked = check_indices(75, 12)
    # only the first checked frame was localized: the frames up to the next checked one
    more = densify(checked, [0], 75)
    assert more == [i for i in range(2, checked[1], 2)]
    assert densify(checked, [], 75) == [] and densify(checked, checked[:6], 75) == []
    assert len(densify(check_indices(600, 50), [0], 600)) == 0  # at most 50 in all


def test_frames_are_added_at_the_maps_spacing_where_they_add_a_view() -> None:
    def camera(x: float, yaw_deg: float = 0.0) -> Rigid3d:
        yaw = np.radians(yaw_deg)
        rotation = np.array(
            [[np.cos(yaw), 0, -np.sin(yaw)], [0, 1, 0], [np.sin(yaw), 0, np.cos(yaw)]]
        )
        return Rigid3d(rotation, -rotation @ np.array([x, 0.0, 0.0]))

    references = [camera(x) for x in np.arange(0.0, 1.0, 0.2)]  # every 20 cm
    assert map_spacing(np.array([r.center for r in references])) == pytest.approx(0.2)
    # a capture every 2 cm from 1 m on, then one frame back in the map turned 90°
    frames = [camera(1.0 + 0.02 * i) for i in range(30)] + [camera(0.4, 90.0)]
    # at a spacing of 19 cm: 1.0, 1.2 and 1.4 m, and the turned view
    assert new_views(frames, references, 0.19) == [0, 10, 20, 30]


def test_frames_beyond_the_anchors_reach_are_not_placed() -> None:
    # a straight 20 m walk, one frame a metre; the map localized frames 2 and 6
    poses = [Rigid3d(np.eye(3), -np.array([float(x), 0.0, 0.0])) for x in range(21)]
    assert anchored(poses, [2, 6], 5.0) == list(range(12))
    assert anchored(poses, [], 5.0) == []
