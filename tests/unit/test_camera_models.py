"""Every COLMAP camera model of the issue "Real clients of the field work unmodified": known to
the engine and the API with pycolmap's parameters, keypoints undistorted through pycolmap
(round trips of synthetic distorted points), intrinsics turned and resized like the images,
and a pose estimated from matches of distorted cameras as from pinhole ones."""

from __future__ import annotations

import typing

import numpy as np
import pycolmap
import pytest

from app.schemas.geometry import CameraModelName, CameraSchema
from services.confidence.model import default_confidence_model
from services.estimators.base import EstimateResult, ReferenceObservation
from services.estimators.options import EstimatorOptions
from services.estimators.ransac import Deadline
from services.estimators.registry import get_estimator
from services.geometry.camera import CAMERA_MODELS, Camera
from services.geometry.intrinsics_adaptation import (
    rotate_camera,
    rotate_points,
    rotated_from_camera,
    scale_camera,
)
from services.geometry.projection import (
    homogeneous,
    normalized_from_pixels,
    pixels_from_camera_points,
    undistort_to_pinhole,
)
from services.localization.estimate import answer_pose
from services.types import FloatArray
from tests.estimators.conftest import TEST_OPTIONS
from tools.synthetic.correspondences import make_correspondences

WIDTH, HEIGHT = 640, 480
# realistic distortion of each model (the focal lengths and principal point are set apart)
DISTORTION: dict[str, tuple[float, ...]] = {
    "SIMPLE_PINHOLE": (),
    "PINHOLE": (),
    "SIMPLE_RADIAL": (-0.12,),
    "RADIAL": (-0.12, 0.03),
    "OPENCV": (-0.12, 0.03, 0.002, -0.001),
    "OPENCV_FISHEYE": (0.05, -0.01, 0.002, -0.0005),
    "FULL_OPENCV": (-0.12, 0.03, 0.002, -0.001, 0.001, 0.01, -0.005, 0.001),
    "FOV": (0.9,),
    "SIMPLE_RADIAL_FISHEYE": (0.05,),
    "RADIAL_FISHEYE": (0.05, -0.01),
    "THIN_PRISM_FISHEYE": (0.05, -0.01, 0.002, -0.001, 0.002, -0.0005, 0.001, -0.002),
    "RAD_TAN_THIN_PRISM_FISHEYE": (
        *(0.05, -0.01, 0.002, -0.0005, 0.0001, 0.0),
        *(0.001, -0.002, 0.001, 0.0002, -0.001, 0.0001),
    ),
}
MODELS = list(CAMERA_MODELS)


def camera_of(model: str, fx: float = 500.0, fy: float = 480.0) -> Camera:
    one_focal = CAMERA_MODELS[model][0] == "f"
    focal = (fx,) if one_focal else (fx, fy)
    return Camera(model, WIDTH, HEIGHT, (*focal, 322.5, 236.0, *DISTORTION[model]))


def colmap(camera: Camera) -> pycolmap.Camera:
    return pycolmap.Camera(
        model=camera.model, width=camera.width, height=camera.height, params=list(camera.params)
    )


def project(camera: Camera, rays: FloatArray) -> FloatArray:
    """(N, 2) pixels of (N, 3) camera-frame rays, by pycolmap."""
    return np.asarray(colmap(camera).img_from_cam(rays), dtype=np.float64)


def test_the_models_are_colmaps_and_the_apis() -> None:
    assert set(DISTORTION) == set(CAMERA_MODELS)
    assert set(typing.get_args(CameraModelName)) == set(CAMERA_MODELS)
    for model, names in CAMERA_MODELS.items():
        info = pycolmap.Camera(model=model, width=WIDTH, height=HEIGHT).params_info
        assert tuple(name.strip() for name in info.split(",")) == names, model


@pytest.mark.parametrize("model", MODELS)
def test_the_api_accepts_the_model(model: str) -> None:
    camera = camera_of(model)
    schema = CameraSchema(
        model=typing.cast(CameraModelName, model),
        width=WIDTH,
        height=HEIGHT,
        params=list(camera.params),
    )
    assert schema.to_camera() == camera


@pytest.mark.parametrize("model", MODELS)
def test_distorted_points_round_trip_through_pycolmap(model: str) -> None:
    """Rays up to 55° off the axis, distorted by pycolmap, come back undistorted onto the
    pinhole camera of the same focal lengths and principal point, to 1e-6 px."""
    camera = camera_of(model)
    rng = np.random.default_rng(len(model))
    angle = np.radians(rng.uniform(0.0, 55.0, 500))
    azimuth = rng.uniform(0.0, 2 * np.pi, 500)
    rays = np.stack(
        [np.tan(angle) * np.cos(azimuth), np.tan(angle) * np.sin(azimuth), np.ones(500)], -1
    )
    distorted = project(camera, rays)
    pinhole, undistorted, kept = undistort_to_pinhole(camera, distorted)
    assert pinhole.model in ("PINHOLE", "SIMPLE_PINHOLE") and not pinhole.distorted
    assert pinhole.focal_lengths == camera.focal_lengths
    assert pinhole.principal_point == camera.principal_point
    assert kept.all()
    expected = rays[:, :2] * np.array(camera.focal_lengths) + np.array(camera.principal_point)
    np.testing.assert_allclose(undistorted, expected, rtol=0, atol=1e-6)
    np.testing.assert_allclose(
        normalized_from_pixels(camera, distorted), rays[:, :2], rtol=0, atol=1e-8
    )
    np.testing.assert_allclose(pixels_from_camera_points(camera, rays), distorted, atol=1e-9)
    if camera.distorted:  # the distortion is real: pinhole coordinates would be off
        assert np.abs(distorted - expected).max() > 1.0


def test_rays_a_pinhole_cannot_hold_are_dropped() -> None:
    """A wide fisheye's corners see rays at 90° and beyond: they are not kept."""
    camera = Camera("OPENCV_FISHEYE", WIDTH, HEIGHT, (150.0, 150.0, 320.0, 240.0, 0, 0, 0, 0))
    _, _, kept = undistort_to_pinhole(camera, np.array([[320.0, 240.0], [0.5, 0.5], [1e6, 0]]))
    assert kept.tolist() == [True, False, False]


@pytest.mark.parametrize("turn", [90, 180, 270])
@pytest.mark.parametrize("model", MODELS)
def test_turned_and_resized_intrinsics_see_the_same_rays(model: str, turn: int) -> None:
    """``rotate_camera`` and a non-uniform ``scale_camera`` give intrinsics under which
    pycolmap projects every ray where the turned, resized image shows it."""
    camera = camera_of(model, 500.0, 500.0)
    rng = np.random.default_rng(turn)
    rays = homogeneous(rng.uniform(-0.5, 0.5, (50, 2)))
    pixels = project(camera, rays)
    turned = rotate_camera(camera, turn)
    np.testing.assert_allclose(
        project(turned, rays @ rotated_from_camera(turn).T),
        rotate_points(pixels, turn, WIDTH, HEIGHT),
        rtol=0,
        atol=1e-9,
    )
    width, height = turned.width // 2 + 1, turned.height // 2  # not exactly uniform
    resized = scale_camera(turned, width, height)
    sx, sy = width / turned.width, height / turned.height
    np.testing.assert_allclose(
        project(resized, rays @ rotated_from_camera(turn).T),
        rotate_points(pixels, turn, WIDTH, HEIGHT) * np.array([sx, sy]),
        rtol=0,
        atol=1e-9,
    )


def _distort(camera: Camera, pinhole: Camera, xy: FloatArray) -> FloatArray:
    """Pixels of ``pinhole`` → the pixels ``camera`` sees the same rays at."""
    return project(camera, homogeneous(normalized_from_pixels(pinhole, xy)))


@pytest.mark.parametrize(
    ("query_model", "reference_model"),
    [
        ("OPENCV", "RADIAL"),
        ("OPENCV_FISHEYE", "FULL_OPENCV"),
        ("FOV", "SIMPLE_RADIAL_FISHEYE"),
        ("THIN_PRISM_FISHEYE", "RAD_TAN_THIN_PRISM_FISHEYE"),
        ("RADIAL_FISHEYE", "SIMPLE_RADIAL"),
    ],
)
def test_a_pose_from_distorted_cameras(query_model: str, reference_model: str) -> None:
    """The synthetic matches seen through distorted cameras of the same focal lengths give
    the pose the pinhole matches give; the answer's masks cover the matches as given and its
    camera is the request's."""
    data = make_correspondences(seed=5, num_references=6, noise_px=0.5)
    pinhole = data.query_camera
    fx, fy = pinhole.focal_lengths
    query_camera = camera_of(query_model, fx, fy)
    ref_camera = camera_of(reference_model, fx, fy)
    references = []
    for ref in data.references:
        references.append(
            ReferenceObservation(
                image_id=ref.image_id,
                camera=ref_camera,
                cam_from_world=ref.cam_from_world,
                query_xy=_distort(query_camera, pinhole, ref.query_xy),
                reference_xy=_distort(ref_camera, ref.camera, ref.reference_xy),
                retrieval_score=ref.retrieval_score,
            )
        )
    seen: list[Camera] = []
    estimator = get_estimator("e5p1")

    class Recording:
        name, needs_depth = estimator.name, estimator.needs_depth

        def estimate(
            self, camera: Camera, refs: list[ReferenceObservation], options: EstimatorOptions
        ) -> EstimateResult:
            seen.extend([camera, *(ref.camera for ref in refs)])
            return estimator.estimate(camera, refs, options)

    answer = answer_pose(
        Recording(),
        query_camera,
        False,
        references,
        TEST_OPTIONS,
        Deadline(None),
        default_confidence_model(),
    )
    result = answer.result
    # the estimator saw pinhole cameras only: pycolmap undistorted every keypoint
    assert seen and not any(camera.distorted for camera in seen)
    assert result.cam_from_world is not None, result.failure_reason
    assert answer.camera == query_camera
    assert [m.shape[0] for m in result.inliers] == [ref.num_matches for ref in references]
    truth = data.query_pose
    center_error = np.linalg.norm(result.cam_from_world.center - truth.center)
    assert center_error < 0.05 * data.scene_depth, center_error
    true_inliers = np.concatenate(data.inlier_masks)
    found = np.concatenate(result.inliers)
    assert (found & true_inliers).sum() > 0.9 * true_inliers.sum()
