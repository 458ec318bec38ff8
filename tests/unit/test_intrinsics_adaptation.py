"""Intrinsics adapted to an upload: quarter turns and resizes checked against pycolmap's
projection, an exact re-render of a turned synthetic image, and the sizes refused."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from services.errors import InvalidInputError
from services.geometry.camera import Camera
from services.geometry.intrinsics_adaptation import (
    QUARTER_TURNS,
    adapt_camera,
    rotate_camera,
    rotate_points,
    rotated_from_camera,
    scale_camera,
)
from services.geometry.rigid import Rigid3d
from tools.synthetic.scene import SyntheticScene

CAMERAS = [
    Camera("SIMPLE_PINHOLE", 640, 480, (500.0, 300.3, 250.7)),
    Camera("PINHOLE", 640, 480, (500.0, 520.0, 300.3, 250.7)),
    Camera("SIMPLE_RADIAL", 640, 480, (500.0, 300.3, 250.7, -0.08)),
    Camera("RADIAL", 640, 480, (500.0, 300.3, 250.7, -0.08, 0.02)),
    Camera("OPENCV", 640, 480, (500.0, 520.0, 300.3, 250.7, 0.1, -0.05, 0.01, -0.02)),
]


def project(camera: Camera, points: np.ndarray) -> np.ndarray:
    """(N, 2) COLMAP pixels of (N, 3) camera-frame points, by pycolmap."""
    colmap = pycolmap.Camera(
        model=camera.model, width=camera.width, height=camera.height, params=list(camera.params)
    )
    return np.asarray(colmap.img_from_cam(points))


@pytest.fixture
def points() -> np.ndarray:
    return np.random.default_rng(0).uniform([-1.0, -0.8, 2.0], [1.0, 0.8, 4.0], (200, 3))


class TestRotateCamera:
    @pytest.mark.parametrize("turn", QUARTER_TURNS)
    @pytest.mark.parametrize("camera", CAMERAS, ids=lambda c: c.model)
    def test_projection_turns_with_the_image(
        self, camera: Camera, turn: int, points: np.ndarray
    ) -> None:
        turned = rotate_camera(camera, turn)
        expected = rotate_points(project(camera, points), turn, camera.width, camera.height)
        actual = project(turned, points @ rotated_from_camera(turn).T)
        np.testing.assert_allclose(actual, expected, atol=1e-9)

    def test_exact_values_90(self) -> None:
        turned = rotate_camera(CAMERAS[4], 90)
        assert (turned.width, turned.height) == (480, 640)
        # fx' = fy, fy' = fx, cx' = H - cy, cy' = cx, (p1', p2') = (p2, -p1)
        assert turned.params == (520.0, 500.0, 480 - 250.7, 300.3, 0.1, -0.05, -0.02, -0.01)

    @pytest.mark.parametrize("turn", (90, 180, 270))
    def test_render_through_turned_camera_is_the_turned_render(self, turn: int) -> None:
        """A ray-cast through the turned camera at the turned pose equals np.rot90 of the
        original render, pixel for pixel (an off-centre principal point and fx != fy)."""
        scene = SyntheticScene(seed=0)
        camera = Camera("PINHOLE", 160, 120, (130.0, 137.0, 74.3, 63.9))
        pose = scene.sample_pose(np.random.default_rng(3))
        image, _ = scene.render(pose, camera)
        R = rotated_from_camera(turn)
        turned, _ = scene.render(
            Rigid3d(R @ pose.rotation, R @ pose.translation), rotate_camera(camera, turn)
        )
        np.testing.assert_array_equal(turned, np.rot90(image, k=-(turn // 90)))

    @pytest.mark.parametrize("turn", QUARTER_TURNS)
    def test_points_round_trip(self, turn: int) -> None:
        xy = np.random.default_rng(1).uniform(0, [640, 480], (50, 2))
        back = rotate_points(
            rotate_points(xy, turn, 640, 480),
            (360 - turn) % 360,
            *((480, 640) if turn in (90, 270) else (640, 480)),
        )
        np.testing.assert_allclose(back, xy, atol=1e-12)

    def test_refuses_other_angles(self) -> None:
        with pytest.raises(ValueError, match="one of"):
            rotate_camera(CAMERAS[0], 45)


class TestScaleCamera:
    @pytest.mark.parametrize("camera", CAMERAS, ids=lambda c: c.model)
    @pytest.mark.parametrize("size", [(320, 240), (213, 160), (1920, 1440)])
    def test_projection_scales_with_the_image(
        self, camera: Camera, size: tuple[int, int], points: np.ndarray
    ) -> None:
        scaled = scale_camera(camera, *size)
        sx, sy = size[0] / camera.width, size[1] / camera.height
        np.testing.assert_allclose(
            project(scaled, points), project(camera, points) * [sx, sy], atol=1e-9
        )

    def test_one_focal_models_gain_a_second_when_not_uniform(self) -> None:
        assert scale_camera(CAMERAS[0], 320, 240).model == "SIMPLE_PINHOLE"
        assert scale_camera(CAMERAS[0], 213, 160).model == "PINHOLE"
        assert scale_camera(CAMERAS[2], 213, 160).model == "OPENCV"


class TestAdaptCamera:
    sensor = Camera("PINHOLE", 1920, 1440, (1500.0, 1500.0, 955.0, 722.0))

    @pytest.mark.parametrize("factor", [1, 2, 3])
    def test_sensor_at_a_multiple_of_the_upload(self, factor: int) -> None:
        camera = Camera(
            "PINHOLE",
            640 * factor,
            480 * factor,
            (500.0 * factor,) * 2
            + (
                320.0 * factor,
                240.0 * factor,
            ),
        )
        adapted = adapt_camera(camera, (640, 480))
        assert adapted.rotation_deg == 0 and adapted.scale == (1 / factor, 1 / factor)
        np.testing.assert_allclose(adapted.camera.params, (500.0, 500.0, 320.0, 240.0))

    def test_portrait_upload_of_landscape_sensor_is_a_clockwise_turn(self) -> None:
        adapted = adapt_camera(self.sensor, (480, 640))
        assert adapted.rotation_deg == 90
        np.testing.assert_allclose(
            adapted.camera.params, (500.0, 500.0, (1440 - 722.0) / 3, 955.0 / 3)
        )

    def test_stated_rotation_wins(self) -> None:
        adapted = adapt_camera(self.sensor, (480, 640), rotation_deg=270)
        assert adapted.rotation_deg == 270
        np.testing.assert_allclose(adapted.camera.params[2:], (722.0 / 3, (1920 - 955.0) / 3))

    def test_exif_turn_of_landscape_pixels(self) -> None:
        """EXIF 6: stored landscape pixels displayed turned 90° clockwise."""
        adapted = adapt_camera(self.sensor, (480, 640), exif_rotation_deg=90, exif_orientation=6)
        assert (adapted.rotation_deg, adapted.exif_orientation) == (90, 6)
        upside_down = adapt_camera(self.sensor, (640, 480), exif_rotation_deg=180)
        assert upside_down.rotation_deg == 180

    def test_rounded_resize_within_a_pixel(self) -> None:
        camera = Camera("SIMPLE_RADIAL", 1920, 1080, (1400.0, 960.0, 540.0, 0.05))
        adapted = adapt_camera(camera, (853, 480))
        assert adapted.camera.model == "OPENCV"
        assert adapted.scale == (853 / 1920, 480 / 1080)

    @pytest.mark.parametrize(
        "upload, rotation",
        [((640, 400), None), ((500, 480), None), ((480, 640), 0), ((640, 480), 90), ((7, 5), None)],
    )
    def test_other_sizes_are_refused_with_the_accepted_ones(
        self, upload: tuple[int, int], rotation: int | None
    ) -> None:
        with pytest.raises(InvalidInputError, match=r"camera is 1920×1440 .* is accepted"):
            adapt_camera(self.sensor, upload, rotation_deg=rotation)

    def test_a_stated_turn_the_sizes_contradict_is_named(self) -> None:
        """The message names what is wrong: not the sizes (640×480 fits 1920×1440 unturned)
        but the stated quarter turn (it once read "camera is 640×480 but the image is
        640×480")."""
        with pytest.raises(InvalidInputError) as raised:
            adapt_camera(self.sensor, (640, 480), rotation_deg=90)
        message = str(raised.value)
        assert "they fit unturned" in message
        assert "camera_rotation_deg = 90° turns the camera's image to 1440×1920" in message
        assert "but the image is" not in message

    def test_sizes_that_fit_no_turn_are_named(self) -> None:
        with pytest.raises(InvalidInputError) as raised:
            adapt_camera(self.sensor, (640, 400))
        assert "the image is 640×400 (as decoded), a size the camera fits neither" in str(
            raised.value
        )
