"""Queries as phones send them, on rendered scenes with exact ground truth: sensor intrinsics
at a multiple of the upload, portrait uploads of a landscape sensor (turned pixels or EXIF),
and the gravity hint. The pose answered is always the uploaded image's."""

from __future__ import annotations

import numpy as np
import pytest

from services.errors import InvalidInputError
from services.geometry.camera import Camera
from services.geometry.intrinsics_adaptation import rotate_camera, rotated_from_camera
from services.geometry.rigid import Rigid3d, pose_error, quaternion_to_matrix
from services.localization.answer import LocalizationResult
from services.localization.localizer import LocalizeParams, Localizer
from services.localization.query_frame import GravityHint, QueryFrameHints
from services.references.memory import MemoryReferenceStore
from tools.synthetic.scene import SyntheticScene, SyntheticView, encode_jpeg, encode_png

WORLD_DOWN = np.array([0.0, 1.0, 0.0])  # the synthetic room's world is y-down


@pytest.fixture(scope="module")
def query(query_views: list[SyntheticView]) -> SyntheticView:
    return query_views[0]


def turned(pose: Rigid3d, turn: int) -> Rigid3d:
    """``pose`` of the camera whose image is turned clockwise by ``turn``."""
    R = rotated_from_camera(turn)
    return Rigid3d(R @ pose.rotation, R @ pose.translation)


def sensor(camera: Camera, factor: float) -> Camera:
    """``camera`` as a sensor ``factor`` times the upload's size gives it."""
    fx, fy, cx, cy = camera.params
    return Camera(
        "PINHOLE",
        round(camera.width * factor),
        round(camera.height * factor),
        (fx * factor, fy * factor, cx * factor, cy * factor),
    )


def assert_localized(
    result: LocalizationResult, truth: Rigid3d, scene: SyntheticScene, max_deg: float = 0.5
) -> None:
    assert result.localized, result.reason
    assert result.cam_from_world is not None
    dt, dr = pose_error(result.cam_from_world, truth)
    assert dt < 0.01 * scene.extent and dr < max_deg, (dt, dr)


@pytest.mark.parametrize("factor", [2, 3])
def test_sensor_intrinsics_at_a_multiple_of_the_upload(
    factor: int,
    localizer: Localizer,
    store: MemoryReferenceStore,
    scene: SyntheticScene,
    query: SyntheticView,
) -> None:
    params = LocalizeParams(camera=sensor(query.camera, factor))
    result = localizer.localize(encode_png(query.image), params, store)
    assert_localized(result, query.cam_from_world, scene)
    assert result.camera_adaptation is not None
    assert result.camera_adaptation.scale == (1 / factor, 1 / factor)
    assert result.camera_adaptation.camera.params == pytest.approx(query.camera.params)


@pytest.mark.parametrize("turn", [90, 270])
def test_portrait_upload_with_turned_intrinsics(
    turn: int,
    localizer: Localizer,
    store: MemoryReferenceStore,
    scene: SyntheticScene,
    query: SyntheticView,
) -> None:
    image = np.ascontiguousarray(np.rot90(query.image, k=-(turn // 90)))
    params = LocalizeParams(camera=rotate_camera(query.camera, turn))
    result = localizer.localize(encode_png(image), params, store)
    assert_localized(result, turned(query.cam_from_world, turn), scene)


@pytest.mark.parametrize("turn", [90, 270])
def test_portrait_upload_with_landscape_sensor_intrinsics(
    turn: int,
    localizer: Localizer,
    store: MemoryReferenceStore,
    scene: SyntheticScene,
    query: SyntheticView,
) -> None:
    """The camera as the phone gives it (landscape, 3× the upload); the turn is stated for
    270°, taken from the sizes (90°) otherwise."""
    image = np.ascontiguousarray(np.rot90(query.image, k=-(turn // 90)))
    hints = QueryFrameHints(camera_rotation_deg=turn if turn == 270 else None)
    params = LocalizeParams(camera=sensor(query.camera, 3), frame=hints)
    result = localizer.localize(encode_png(image), params, store)
    assert_localized(result, turned(query.cam_from_world, turn), scene)
    assert result.camera_adaptation is not None
    assert result.camera_adaptation.rotation_deg == turn


@pytest.mark.parametrize("orientation, turn", [(6, 90), (8, 270), (3, 180)])
def test_exif_oriented_jpeg(
    orientation: int,
    turn: int,
    localizer: Localizer,
    store: MemoryReferenceStore,
    scene: SyntheticScene,
    query: SyntheticView,
) -> None:
    """Landscape pixels stored with an EXIF orientation, the camera given for those pixels:
    the answer is the pose of the image as displayed (turned by the EXIF orientation)."""
    data = encode_jpeg(query.image, orientation)
    result = localizer.localize(data, LocalizeParams(camera=sensor(query.camera, 2)), store)
    assert_localized(result, turned(query.cam_from_world, turn), scene)
    assert result.camera_adaptation is not None
    assert result.camera_adaptation.exif_orientation == orientation
    assert result.camera_adaptation.rotation_deg == turn


def test_sizes_that_no_scale_and_turn_relate_are_refused(
    localizer: Localizer, store: MemoryReferenceStore, query: SyntheticView
) -> None:
    camera = Camera("PINHOLE", 800, 480, (500.0, 500.0, 400.0, 240.0))
    with pytest.raises(InvalidInputError, match="640×480 or 480×640"):
        localizer.localize(encode_png(query.image), LocalizeParams(camera=camera), store)


def gravity_in_camera(pose: Rigid3d, off_deg: float = 0.0) -> np.ndarray:
    """World down seen from ``pose``, turned ``off_deg`` about the camera's optical axis."""
    half = np.radians(off_deg) / 2
    spin = quaternion_to_matrix(np.array([np.cos(half), 0.0, 0.0, np.sin(half)]))
    down: np.ndarray = spin @ pose.rotation @ WORLD_DOWN
    return down


@pytest.mark.parametrize("turn", [0, 90, 180])
def test_gravity_turns_the_query_upright_and_checks_the_pose(
    turn: int,
    localizer: Localizer,
    store: MemoryReferenceStore,
    scene: SyntheticScene,
    query: SyntheticView,
) -> None:
    truth = turned(query.cam_from_world, turn)
    image = np.ascontiguousarray(np.rot90(query.image, k=-(turn // 90)))
    hint = GravityHint(gravity_in_camera(truth), max_angle_deg=2.0, map_down=WORLD_DOWN)
    frame = QueryFrameHints(gravity=hint)
    camera = rotate_camera(query.camera, turn)
    result = localizer.localize(encode_png(image), LocalizeParams(camera, frame=frame), store)
    assert_localized(result, truth, scene)
    assert result.upright_turn_deg == (360 - turn) % 360
    assert result.stats["gravity_error_deg"] < 0.5


def test_gravity_in_the_camera_frame_is_turned_with_it(
    localizer: Localizer, store: MemoryReferenceStore, scene: SyntheticScene, query: SyntheticView
) -> None:
    """Gravity given in the landscape sensor's frame, the upload portrait."""
    image = np.ascontiguousarray(np.rot90(query.image, k=-1))
    hint = GravityHint(gravity_in_camera(query.cam_from_world), map_down=WORLD_DOWN)
    params = LocalizeParams(camera=sensor(query.camera, 3), frame=QueryFrameHints(gravity=hint))
    result = localizer.localize(encode_png(image), params, store)
    assert_localized(result, turned(query.cam_from_world, 90), scene)
    assert result.upright_turn_deg == 270
    assert result.stats["gravity_error_deg"] < 0.5


def test_pose_against_gravity_is_rejected(
    localizer: Localizer, store: MemoryReferenceStore, query: SyntheticView
) -> None:
    hint = GravityHint(gravity_in_camera(query.cam_from_world, off_deg=10.0), max_angle_deg=5.0)
    params = LocalizeParams(camera=query.camera, frame=QueryFrameHints(gravity=hint))
    result = localizer.localize(encode_png(query.image), params, store)
    assert not result.localized and result.cam_from_world is None
    assert result.reason == "gravity_mismatch"
    assert result.stats["gravity_error_deg"] > 5.0
    assert result.num_inliers == 0


def test_map_down_defaults_to_the_references_mean(
    localizer: Localizer, store: MemoryReferenceStore, query: SyntheticView
) -> None:
    """References captured roughly upright (pitch ±8°, roll ±5°): their mean down is within
    a few degrees of the truth."""
    hint = GravityHint(gravity_in_camera(query.cam_from_world), max_angle_deg=5.0)
    params = LocalizeParams(camera=query.camera, frame=QueryFrameHints(gravity=hint))
    result = localizer.localize(encode_png(query.image), params, store)
    assert result.localized
    assert result.stats["gravity_error_deg"] < 3.0
