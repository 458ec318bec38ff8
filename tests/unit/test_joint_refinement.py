"""The query pose refined jointly with its points (``services.geometry.joint_refinement``):
checked against COLMAP's bundle adjustment (pycolmap, Ceres) on the same problem, and for what
it is for, on synthetic forward motion with exact ground truth: references 2.3 m apart along a
road, a query a metre past the last, points 10–50 m ahead seen under a few degrees."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap

from services.estimators.poselib_bridge import refine_absolute_pose
from services.geometry.camera import Camera
from services.geometry.joint_refinement import PointObservations, RigViews, refine_pose_and_points
from services.geometry.rigid import Rigid3d
from services.geometry.triangulation import triangulate_dlt
from services.types import FloatArray

FOCAL = 700.0
NOISE_PX = 0.7
LOSS_PX = 2.0
CAMERA = Camera("PINHOLE", 1226, 370, (FOCAL, FOCAL, 0.0, 0.0))


def _camera(center: tuple[float, float, float], yaw: float) -> Rigid3d:
    rotation = np.asarray(cv2.Rodrigues(np.array([0.0, yaw, 0.0]))[0], dtype=np.float64)
    return Rigid3d(rotation, -rotation @ np.asarray(center))


def _normalized(pose: Rigid3d, points: FloatArray, rng: np.random.Generator) -> FloatArray:
    in_camera = pose.apply(points)
    return in_camera[:, :2] / in_camera[:, 2:3] + rng.normal(
        0.0, NOISE_PX / FOCAL, (len(points), 2)
    )


def forward_scene(
    seed: int,
) -> tuple[Rigid3d, FloatArray, FloatArray, PointObservations, Rigid3d, FloatArray]:
    """The query's true pose, the points triangulated from two references (DLT), the query's
    noisy observations of them, the references' observations, the pose fitted to the
    triangulated points as if they were exact (PoseLib's refinement from the truth), and the
    points' true positions."""
    rng = np.random.default_rng(seed)
    references = [_camera((0.0, 0.0, 0.0), 0.0), _camera((0.0, 0.0, 2.3), 0.01)]
    query = _camera((0.3, 0.0, 3.3), 0.02)
    count = 300
    world = np.stack(
        [rng.uniform(-15, 15, count), rng.uniform(-3, 3, count), rng.uniform(10, 50, count)], 1
    )
    seen = [_normalized(r, world, rng) for r in references]
    points = triangulate_dlt(
        np.stack(seen, axis=1), np.stack([r.matrix for r in references]), np.ones((count, 2))
    )
    ahead = np.all([r.apply(points)[:, 2] > 0 for r in (*references, query)], axis=0)
    ahead &= np.linalg.norm(points - world, axis=1) < 20.0
    points, seen = points[ahead], [s[ahead] for s in seen]
    kept = len(points)
    query_normalized = _normalized(query, world[ahead], rng)
    observations = PointObservations(
        point_of=np.tile(np.arange(kept), 2),
        camera_of=np.repeat([0, 1], kept),
        normalized=np.concatenate(seen),
        rotations=np.stack([r.rotation for r in references]),
        translations=np.stack([r.translation for r in references]),
        focals=np.full(2, FOCAL),
    )
    two_step = refine_absolute_pose(query_normalized * FOCAL, points, CAMERA, query, LOSS_PX)
    return query, points, query_normalized, observations, two_step, world[ahead]


def colmap_bundle_adjustment(
    pose: Rigid3d, points: FloatArray, query_normalized: FloatArray, refs: PointObservations
) -> Rigid3d:
    """The same problem solved by COLMAP: the references' poses and every camera's intrinsics
    constant, the query's pose and the points free, Cauchy loss at ``LOSS_PX``."""
    reconstruction = pycolmap.Reconstruction()
    config = pycolmap.BundleAdjustmentConfig()
    poses = [*(Rigid3d(r, t) for r, t in zip(refs.rotations, refs.translations, strict=True))]
    seen = [refs.normalized[refs.camera_of == c] for c in range(len(poses))]
    tracks = [pycolmap.Track() for _ in points]
    for image_id, (camera_pose, xy) in enumerate(
        zip([*poses, pose], [*seen, query_normalized], strict=True), start=1
    ):
        reconstruction.add_camera_with_trivial_rig(
            pycolmap.Camera(
                model="SIMPLE_PINHOLE", width=1, height=1, params=[FOCAL, 0, 0], camera_id=image_id
            )
        )
        image = pycolmap.Image(name=str(image_id), camera_id=image_id, image_id=image_id)
        image.points2D = pycolmap.Point2DList([pycolmap.Point2D(p * FOCAL) for p in xy])
        w, x, y, z = camera_pose.quaternion
        reconstruction.add_image_with_trivial_frame(
            image,
            pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([x, y, z, w])), camera_pose.translation),
        )
        for index in range(len(xy)):
            tracks[index].add_element(image_id, index)
        config.add_image(image_id)
        config.set_constant_cam_intrinsics(image_id)
        if image_id <= len(poses):
            config.set_constant_rig_from_world_pose(reconstruction.image(image_id).frame_id)
    for point, track in zip(points, tracks, strict=True):
        reconstruction.add_point3D(point, track)
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = LOSS_PX
    summary = pycolmap.create_default_bundle_adjuster(options, config, reconstruction).solve()
    assert summary.is_solution_usable()
    solved = reconstruction.image(len(poses) + 1).cam_from_world()
    return Rigid3d(solved.rotation.matrix(), np.asarray(solved.translation, dtype=np.float64))


def test_agrees_with_colmaps_bundle_adjustment() -> None:
    for seed in range(3):
        _, points, query_normalized, refs, two_step, _ = forward_scene(seed)
        colmap = colmap_bundle_adjustment(two_step, points, query_normalized, refs)
        ours, _ = refine_pose_and_points(
            two_step, points, query_normalized, FOCAL, refs, LOSS_PX, iterations=20
        )
        moved = np.linalg.norm(colmap.center - two_step.center)
        assert moved > 1e-3  # the adjustment moves the pose: the agreement is not vacuous
        assert np.linalg.norm(ours.center - colmap.center) < 0.02 * moved
        turned = np.linalg.norm(cv2.Rodrigues(ours.rotation @ colmap.rotation.T)[0])
        assert np.degrees(turned) < 1e-3


def test_places_a_forward_query_better_than_the_points_taken_as_exact() -> None:
    two_step_errors, joint_errors = [], []
    for seed in range(20):
        truth, points, query_normalized, refs, two_step, _ = forward_scene(seed)
        joint, refined_points = refine_pose_and_points(
            two_step, points, query_normalized, FOCAL, refs, LOSS_PX
        )
        assert refined_points.shape == points.shape
        two_step_errors.append(np.linalg.norm(two_step.center - truth.center))
        joint_errors.append(np.linalg.norm(joint.center - truth.center))
    # 14 of 20 closer, the mean error 0.69 times the points-as-exact one
    assert np.mean(joint_errors) < 0.8 * np.mean(two_step_errors)
    assert sum(j < t for j, t in zip(joint_errors, two_step_errors, strict=True)) >= 12


def test_exact_observations_stay_where_they_are() -> None:
    rng = np.random.default_rng(0)
    references = [_camera((0.0, 0.0, 0.0), 0.0), _camera((1.0, 0.0, 0.5), -0.05)]
    query = _camera((0.5, 0.2, 1.5), 0.03)
    world = rng.uniform([-5, -2, 8], [5, 2, 20], (50, 3))

    def exact(pose: Rigid3d) -> FloatArray:
        in_camera = pose.apply(world)
        return in_camera[:, :2] / in_camera[:, 2:3]

    refs = PointObservations(
        point_of=np.tile(np.arange(50), 2),
        camera_of=np.repeat([0, 1], 50),
        normalized=np.concatenate([exact(r) for r in references]),
        rotations=np.stack([r.rotation for r in references]),
        translations=np.stack([r.translation for r in references]),
        focals=np.full(2, FOCAL),
    )
    pose, points = refine_pose_and_points(query, world, exact(query), FOCAL, refs, LOSS_PX)
    assert np.linalg.norm(pose.center - query.center) < 1e-9
    assert np.abs(points - world).max() < 1e-9


def test_a_rig_of_one_camera_is_the_single_camera_refinement() -> None:
    _, points, query_normalized, refs, two_step, _ = forward_scene(0)
    single, single_points = refine_pose_and_points(
        two_step, points, query_normalized, FOCAL, refs, LOSS_PX
    )
    rig = RigViews([Rigid3d(np.eye(3), np.zeros(3))], np.array([FOCAL]), np.zeros(len(points), int))
    ours, our_points = refine_pose_and_points(
        two_step, points, query_normalized, 0.0, refs, LOSS_PX, rig=rig
    )
    assert np.linalg.norm(ours.center - single.center) < 1e-9
    assert np.abs(our_points - single_points).max() < 1e-9


def test_a_rig_places_its_first_camera_better_than_one_camera() -> None:
    """Two frames of a session a metre apart on the forward scene, each with its own copy of
    the points the references triangulated (as the several-frame estimator keeps them):
    refined together, the second frame fixed to the first, the first lies closer to the truth
    than refined alone."""
    alone_errors, rig_errors = [], []
    for seed in range(20):
        truth, points, query_normalized, refs, two_step, world = forward_scene(seed)
        second = _camera((-0.3, 0.0, 4.3), 0.0)
        visible = second.apply(world)[:, 2] > 0
        second_normalized = _normalized(second, world[visible], np.random.default_rng(100 + seed))
        alone, _ = refine_pose_and_points(two_step, points, query_normalized, FOCAL, refs, LOSS_PX)
        kept = int(visible.sum())
        index = np.flatnonzero(visible)
        copy_of = np.full(len(points), -1)
        copy_of[index] = len(points) + np.arange(kept)
        seen = np.isin(refs.point_of, index)
        both = PointObservations(
            point_of=np.concatenate([refs.point_of, copy_of[refs.point_of[seen]]]),
            camera_of=np.concatenate([refs.camera_of, refs.camera_of[seen]]),
            normalized=np.concatenate([refs.normalized, refs.normalized[seen]]),
            rotations=refs.rotations,
            translations=refs.translations,
            focals=refs.focals,
        )
        rig = RigViews(
            [Rigid3d(np.eye(3), np.zeros(3)), second.compose(truth.inverse())],
            np.full(2, FOCAL),
            np.repeat([0, 1], [len(points), kept]),
        )
        joint, _ = refine_pose_and_points(
            two_step,
            np.concatenate([points, points[visible]]),
            np.concatenate([query_normalized, second_normalized]),
            0.0,
            both,
            LOSS_PX,
            rig=rig,
        )
        alone_errors.append(np.linalg.norm(alone.center - truth.center))
        rig_errors.append(np.linalg.norm(joint.center - truth.center))
    # 12 of 20 closer, the mean error 0.82 times one camera's
    assert np.mean(rig_errors) < 0.9 * np.mean(alone_errors)
