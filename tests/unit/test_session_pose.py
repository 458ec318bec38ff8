"""AR-session poses (OpenGL camera axes) ↔ the engine's ``cam_from_session``."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.errors import InvalidInputError
from services.geometry.rigid import Rigid3d
from services.geometry.session_pose import (
    cam_from_session,
    homogeneous,
    rigid_from_matrix,
    session_from_camera_opengl,
)


class TestCamFromSession:
    def test_identity_device_pose_looks_down_minus_z(self) -> None:
        # an ARKit camera at the session origin with identity transform looks along −z with
        # y up: a point 2 m in front of it is at session (0, 0, −2), above it at +y
        pose = cam_from_session(Rigid3d.identity())
        in_front = pose.apply(np.array([[0.0, 0.0, -2.0], [0.0, 1.0, -2.0]]))
        np.testing.assert_allclose(in_front, [[0.0, 0.0, 2.0], [0.0, -1.0, 2.0]])

    def test_translated_device(self) -> None:
        device = Rigid3d(np.eye(3), np.array([1.0, 2.0, 3.0]))
        pose = cam_from_session(device)
        np.testing.assert_allclose(pose.center, [1.0, 2.0, 3.0])
        np.testing.assert_allclose(pose.apply(np.array([[1.0, 2.0, 1.0]])), [[0.0, 0.0, 2.0]])

    def test_round_trip(self) -> None:
        rng = np.random.default_rng(3)
        for _ in range(5):
            truth = Rigid3d(cv2.Rodrigues(rng.normal(size=3))[0], rng.normal(size=3))
            back = cam_from_session(session_from_camera_opengl(truth))
            np.testing.assert_allclose(back.matrix, truth.matrix, atol=1e-12)


class TestRigidFromMatrix:
    def test_accepts_a_rigid_matrix(self) -> None:
        truth = Rigid3d(cv2.Rodrigues(np.array([0.2, -0.4, 0.1]))[0], np.array([1.0, 2.0, 3.0]))
        out = rigid_from_matrix(homogeneous(truth).astype(np.float32))
        np.testing.assert_allclose(out.matrix, truth.matrix, atol=1e-6)
        np.testing.assert_allclose(out.rotation @ out.rotation.T, np.eye(3), atol=1e-12)

    @pytest.mark.parametrize(
        ("matrix", "fragment"),
        [
            (np.eye(4)[:3], "must be 4×4"),
            (np.diag([2.0, 2.0, 2.0, 1.0]), "not a rotation"),
            (np.diag([1.0, 1.0, -1.0, 1.0]), "not a rotation"),
            (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [1, 2, 3, 1]], float), "last row"),
            (np.full((4, 4), np.nan), "finite"),
        ],
    )
    def test_refuses(self, matrix: np.ndarray, fragment: str) -> None:
        with pytest.raises(InvalidInputError, match=fragment):
            rigid_from_matrix(matrix)
