"""EXIF orientation, pose conventions and gravity: the pure parts of AR client support."""

from __future__ import annotations

import numpy as np
import pytest

from services.errors import InvalidInputError
from services.geometry.gravity import (
    gravity_error_deg,
    references_down,
    upright_turn,
)
from services.geometry.intrinsics_adaptation import rotated_from_camera
from services.geometry.pose_conventions import (
    POSE_CONVENTIONS,
    cam_from_world_of,
    world_from_cam,
)
from services.geometry.rigid import Rigid3d, quaternion_to_matrix
from services.imaging.decode import decode_image
from services.localization.exif_orientation import (
    MIRRORED_ORIENTATIONS,
    ORIENTATION_ROTATION_DEG,
    exif_orientation,
    orientation_rotation_deg,
)
from tools.synthetic.scene import encode_jpeg, encode_png


def random_pose(seed: int) -> Rigid3d:
    rng = np.random.default_rng(seed)
    return Rigid3d.from_quaternion(rng.normal(size=4), rng.normal(size=3))


class TestExifOrientation:
    image = np.zeros((48, 64, 3), np.uint8)

    @pytest.mark.parametrize("orientation", [1, 3, 6, 8])
    def test_the_turn_named_is_the_turn_decoding_applies(self, orientation: int) -> None:
        """OpenCV's decoder turns the stored pixels; the tag read here says by how much."""
        marked = self.image.copy()
        marked[:8, :8] = 255  # top-left corner of the stored pixels
        data = encode_jpeg(marked, orientation)
        assert exif_orientation(data) == orientation
        decoded = decode_image(data, 10**6)
        turn = orientation_rotation_deg(orientation)
        expected = np.rot90(marked, k=-(turn // 90))
        assert decoded.shape == expected.shape
        assert abs(decoded.astype(int) - expected).mean() < 3

    def test_absent(self) -> None:
        assert exif_orientation(encode_jpeg(self.image)) is None
        assert exif_orientation(encode_png(self.image)) is None
        assert orientation_rotation_deg(None) == 0

    def test_big_endian_tiff(self) -> None:
        data = encode_jpeg(self.image)
        tiff = b"MM\x00*" + bytes.fromhex("00000008 0001 0112 0003 00000001 0008 0000 00000000")
        payload = b"Exif\x00\x00" + tiff
        app1 = b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload
        assert exif_orientation(data[:2] + app1 + data[2:]) == 8

    def test_corrupt_block_is_no_orientation(self) -> None:
        data = encode_jpeg(self.image)
        payload = b"Exif\x00\x00II*\x00\xff\xff\xff\x00"
        app1 = b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload
        assert exif_orientation(data[:2] + app1 + data[2:]) is None

    @pytest.mark.parametrize("orientation", MIRRORED_ORIENTATIONS)
    def test_mirrored_orientations_are_refused(self, orientation: int) -> None:
        with pytest.raises(InvalidInputError, match="mirrors"):
            orientation_rotation_deg(orientation)

    def test_table(self) -> None:
        assert ORIENTATION_ROTATION_DEG == {1: 0, 3: 180, 6: 90, 8: 270}


class TestPoseConventions:
    @pytest.mark.parametrize("convention", POSE_CONVENTIONS)
    def test_round_trip(self, convention: str) -> None:
        pose = random_pose(0)
        back = cam_from_world_of(world_from_cam(pose, convention), convention)
        np.testing.assert_allclose(back.rotation, pose.rotation, atol=1e-12)
        np.testing.assert_allclose(back.translation, pose.translation, atol=1e-12)

    def test_axes(self) -> None:
        """Where each convention's camera axes point, for one pose."""
        pose = random_pose(1)
        colmap = world_from_cam(pose, "colmap")
        opengl = world_from_cam(pose, "opengl")
        unity = world_from_cam(pose, "unity")
        right, down, forward = colmap[:3, 0], colmap[:3, 1], colmap[:3, 2]
        np.testing.assert_allclose(colmap[:3, 3], pose.center, atol=1e-12)
        np.testing.assert_allclose(opengl[:3, :3], np.stack([right, -down, -forward], 1))
        np.testing.assert_allclose(opengl[:3, 3], pose.center)
        mirror = np.diag([1.0, 1.0, -1.0])  # Unity's world: the map mirrored along z
        np.testing.assert_allclose(
            unity[:3, :3], np.stack([mirror @ right, -mirror @ down, mirror @ forward], 1)
        )
        np.testing.assert_allclose(unity[:3, 3], mirror @ pose.center)
        for matrix in (colmap, opengl, unity):
            assert np.linalg.det(matrix[:3, :3]) == pytest.approx(1.0)

    def test_worked_example(self) -> None:
        """README's example: a camera at (1, 2, 3) looking along the map's +x, image down
        along the map's -y (as in a y-up map)."""
        world_from_cam_colmap = np.array([[0, 0, 1], [0, -1, 0], [1, 0, 0]], float)
        center = np.array([1.0, 2.0, 3.0])
        R = world_from_cam_colmap.T
        pose = Rigid3d(R, -R @ center)
        np.testing.assert_allclose(
            world_from_cam(pose, "opengl"),
            [[0, 0, -1, 1], [0, 1, 0, 2], [1, 0, 0, 3], [0, 0, 0, 1]],
            atol=1e-12,
        )
        np.testing.assert_allclose(
            world_from_cam(pose, "unity"),
            [[0, 0, 1, 1], [0, 1, 0, 2], [-1, 0, 0, -3], [0, 0, 0, 1]],
            atol=1e-12,
        )

    def test_unknown(self) -> None:
        with pytest.raises(ValueError, match="known: colmap, opengl, unity"):
            world_from_cam(random_pose(0), "vulkan")


class TestGravity:
    @pytest.mark.parametrize("turn", [0, 90, 180, 270])
    def test_upright_turn_undoes_a_turn(self, turn: int) -> None:
        down = np.array([0.1, 0.9, 0.3])  # a level-ish upright camera
        turned = rotated_from_camera(turn) @ down
        undo = upright_turn(turned)
        assert undo == (360 - turn) % 360
        assert (rotated_from_camera(undo) @ turned)[1] > 0.8

    def test_no_turn_looking_straight_down(self) -> None:
        assert upright_turn(np.array([0.05, 0.1, 1.0])) is None

    def test_references_down_and_error(self) -> None:
        rng = np.random.default_rng(0)
        down = np.array([0.0, 0.0, -1.0])  # a z-up map
        poses = []
        for _ in range(20):  # upright cameras: image +y along the map's down, random yaw
            yaw = rng.uniform(0, 2 * np.pi)
            forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
            right = np.cross(forward, -down)
            R = np.stack([right, down, forward])  # rows: camera axes in the world
            poses.append(Rigid3d(R, rng.normal(size=3)))
        np.testing.assert_allclose(references_down(poses), down, atol=1e-12)
        tilt = quaternion_to_matrix(
            np.array([np.cos(np.radians(4)), 0.0, 0.0, np.sin(np.radians(4))])
        )
        measured = tilt @ poses[0].rotation @ down  # gravity 8° off in the image plane
        assert gravity_error_deg(poses[0], measured, down) == pytest.approx(8.0)
