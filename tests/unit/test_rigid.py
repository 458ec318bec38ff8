import numpy as np
import pycolmap
import pytest

from services.geometry.rigid import (
    Rigid3d,
    matrix_to_quaternion,
    pose_error,
    quaternion_to_matrix,
    rotation_error_deg,
)


def _random_quaternions(n: int) -> np.ndarray:
    q = np.random.default_rng(0).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


class TestQuaternion:
    def test_matches_pycolmap(self) -> None:
        for q in _random_quaternions(50):
            # pycolmap stores [x, y, z, w]
            expected = pycolmap.Rotation3d(np.array([q[1], q[2], q[3], q[0]])).matrix()
            assert np.allclose(quaternion_to_matrix(q), expected, atol=1e-12)

    def test_round_trip_all_branches(self) -> None:
        # include rotations by ~180° about each axis, which exercise every Shepperd branch
        qs = [
            *_random_quaternions(50),
            np.array([0.0, 1, 0, 0]),
            np.array([0.0, 0, 1, 0]),
            np.array([0.0, 0, 0, 1]),
            np.array([0.01, 0.7, 0.7, 0.1]),
        ]
        for q in qs:
            q = q / np.linalg.norm(q)
            back = matrix_to_quaternion(quaternion_to_matrix(q))
            assert back[0] >= 0
            assert np.isclose(abs(back @ q), 1.0, atol=1e-12)


class TestRigid3d:
    def test_inverse_compose_center(self) -> None:
        rng = np.random.default_rng(1)
        pose = Rigid3d.from_quaternion(_random_quaternions(1)[0], rng.normal(size=3))
        ident = pose.compose(pose.inverse())
        assert np.allclose(ident.rotation, np.eye(3)) and np.allclose(ident.translation, 0)
        # the centre maps to the camera origin
        assert np.allclose(pose.apply(pose.center[None])[0], 0.0)

    def test_apply_batch_equals_loop(self) -> None:
        pose = Rigid3d.from_quaternion(_random_quaternions(1)[0], np.array([1.0, 2, 3]))
        points = np.random.default_rng(2).normal(size=(7, 3))
        loop = np.stack([pose.rotation @ p + pose.translation for p in points])
        assert np.allclose(pose.apply(points), loop)

    def test_errors(self) -> None:
        a = Rigid3d.identity()
        R = quaternion_to_matrix(np.array([np.cos(np.radians(5)), 0, np.sin(np.radians(5)), 0]))
        b = Rigid3d(R, -R @ np.array([3.0, 4.0, 0.0]))
        dt, dr = pose_error(b, a)
        assert dt == pytest.approx(5.0) and dr == pytest.approx(10.0)
        assert rotation_error_deg(R, R) == pytest.approx(0.0, abs=1e-6)


def test_epipolar_errors_zero_for_true_matches_and_exact_for_a_shift() -> None:
    from services.geometry.camera import Camera
    from services.geometry.epipolar import epipolar_errors

    camera = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
    rng = np.random.default_rng(3)
    points = rng.uniform([-1, -1, 4], [1, 1, 6], size=(20, 3))
    a = Rigid3d(np.eye(3), np.zeros(3))
    b = Rigid3d(np.eye(3), np.array([-1.0, 0.0, 0.0]))  # camera b one unit to the right
    xy_a = (points[:, :2] / points[:, 2:]) * 500.0 + [320.0, 240.0]
    xy_b = ((points[:, :2] + [-1.0, 0.0]) / points[:, 2:]) * 500.0 + [320.0, 240.0]
    np.testing.assert_allclose(epipolar_errors(camera, a, xy_a, camera, b, xy_b), 0.0, atol=1e-9)
    # a pure sideways baseline has horizontal epipolar lines: a 3 px vertical shift is 3 px off
    shifted = xy_b + np.array([0.0, 3.0])
    np.testing.assert_allclose(epipolar_errors(camera, a, xy_a, camera, b, shifted), 3.0)
