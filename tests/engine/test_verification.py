"""Post-estimation verification: unrelated images are rejected, true queries still accepted.

Unit tests of ``verify_by_reference_triangulation`` on exact geometry, then the whole
pipeline (SIFT → thumbnail retrieval → NN matching → E5+1 → verification) on a rendered
synthetic map of 20 references.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from services.estimators import verification
from services.estimators.base import EstimateResult, FailureReason, ReferenceObservation
from services.estimators.options import EstimatorOptions, VerificationOptions
from services.estimators.uncertainty import pose_uncertainty
from services.estimators.verification import StructureCheck, verify_by_reference_triangulation
from services.features.sift import SiftExtractor
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d, pose_error
from services.localization.localizer import LocalizeParams, Localizer
from services.matching.nearest_neighbor import NearestNeighborMatcher
from services.references.store import ReferenceView
from services.retrieval.contracts import RetrievalIndex
from services.retrieval.thumbnail import ThumbnailDescriptor
from tools.synthetic.scene import SyntheticScene, encode_png, unrelated_image

# ---------------------------------------------------------------- unit: exact geometry


def _look_at(center: NDArray[np.float64], yaw_deg: float) -> Rigid3d:
    yaw = np.radians(yaw_deg)
    world_from_cam = np.array(
        [[np.cos(yaw), 0.0, np.sin(yaw)], [0.0, 1.0, 0.0], [-np.sin(yaw), 0.0, np.cos(yaw)]]
    )
    R = world_from_cam.T
    return Rigid3d(R, -R @ center)


def _normalized(pose: Rigid3d, points: NDArray[np.float64]) -> NDArray[np.float64]:
    cam = pose.apply(points)
    out: NDArray[np.float64] = cam[:, :2] / cam[:, 2:]
    return out


_CAMERA = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))


def _pixels(pose: Rigid3d, points: NDArray[np.float64]) -> NDArray[np.float64]:
    out: NDArray[np.float64] = _normalized(pose, points) * 500.0 + [320.0, 240.0]
    return out


class _Setup:
    """P points seen by three references and the query; correspondences ordered by reference."""

    def __init__(self, seed: int = 0, num_points: int = 40) -> None:
        rng = np.random.default_rng(seed)
        self.points = rng.uniform([-2, -1, 4], [2, 1, 7], (num_points, 3))
        self.references = [
            _look_at(np.array([-0.6, 0.0, 0.0]), 5.0),
            _look_at(np.array([0.0, 0.1, 0.2]), 0.0),
            _look_at(np.array([0.7, -0.1, 0.0]), -5.0),
        ]
        self.query = _look_at(np.array([0.2, 0.05, 0.5]), 2.0)
        n = len(self.references)
        self.reference_index = np.repeat(np.arange(n), num_points).astype(np.int64)
        self.track_ids = np.tile(np.arange(num_points), n).astype(np.int64)
        self.reference_normalized = np.concatenate(
            [_normalized(ref, self.points) for ref in self.references]
        )
        self.rotations = np.stack([ref.rotation for ref in self.references])
        self.translations = np.stack([ref.translation for ref in self.references])
        self.threshold = 2.0 / 500.0  # 2 px at f = 500

    def check(
        self, query: Rigid3d, reference_normalized: NDArray[np.float64] | None = None
    ) -> StructureCheck:
        return verify_by_reference_triangulation(
            query.rotation,
            query.translation,
            _normalized(query, self.points)[self.track_ids],
            self.reference_index,
            self.rotations,
            self.translations,
            self.reference_normalized if reference_normalized is None else reference_normalized,
            self.track_ids,
            self.threshold,
            np.full(len(self.references), self.threshold),
        )


def test_exact_geometry_verifies_every_point() -> None:
    setup = _Setup()
    check = setup.check(setup.query)
    assert check.num_tracks == 40
    assert check.num_verified_points == 40
    assert check.correspondence_verified.all()
    np.testing.assert_allclose(check.points, setup.points, atol=1e-9)


def test_wrong_query_pose_verifies_nothing() -> None:
    setup = _Setup()
    # the query's observations come from the true pose, the pose to verify is rotated by 3°
    truth = setup.query
    turned = Rigid3d(_look_at(np.zeros(3), 3.0).rotation @ truth.rotation, truth.translation)
    check = verify_by_reference_triangulation(
        turned.rotation,
        turned.translation,
        _normalized(truth, setup.points)[setup.track_ids],
        setup.reference_index,
        setup.rotations,
        setup.translations,
        setup.reference_normalized,
        setup.track_ids,
        setup.threshold,
        np.full(3, setup.threshold),
    )
    assert check.num_tracks == 40
    assert check.num_verified_points == 0


def test_disagreeing_reference_observation_is_dropped() -> None:
    setup = _Setup()
    corrupted = setup.reference_normalized.copy()
    corrupted[0] += [0.05, -0.04]  # point 0 in reference 0 moved by ~30 px
    check = setup.check(setup.query, corrupted)
    assert check.num_verified_points == 40  # two agreeing references remain for point 0
    assert not check.correspondence_verified[0]
    assert check.correspondence_verified[1:].all()


def test_single_reference_tracks_and_parallel_rays_are_not_verified() -> None:
    setup = _Setup()
    same_center = np.stack([setup.references[1].rotation] * 3)
    check = verify_by_reference_triangulation(
        setup.query.rotation,
        setup.query.translation,
        _normalized(setup.query, setup.points)[setup.track_ids],
        setup.reference_index,
        same_center,  # every reference at the same pose: rays parallel, depth undetermined
        np.stack([setup.references[1].translation] * 3),
        np.tile(_normalized(setup.references[1], setup.points), (3, 1)),
        setup.track_ids,
        setup.threshold,
        np.full(3, setup.threshold),
    )
    assert check.num_verified_points == 0
    only_first = setup.reference_index == 0
    single = verify_by_reference_triangulation(
        setup.query.rotation,
        setup.query.translation,
        _normalized(setup.query, setup.points),
        setup.reference_index[only_first],
        setup.rotations,
        setup.translations,
        setup.reference_normalized[only_first],
        setup.track_ids[only_first],
        setup.threshold,
        np.full(3, setup.threshold),
    )
    assert single.num_tracks == 0
    assert single.num_verified_points == 0


def test_parallel_agreeing_rays_leave_the_track_untriangulated() -> None:
    """Regression (singular matrix on a driving frame): two far references on one line see the
    point straight ahead, so their rays are the same line; a near reference whose ray misses
    it by 0.02 pairs with one of them into a hypothesis the far two agree with and it does
    not. The agreeing rays are then exactly parallel and their system singular: the track
    stays untriangulated instead of raising."""
    identity = np.eye(3)
    centers = np.array([[0.0, 0.0, -100.0], [1.0, 0.0, 4.0], [0.0, 0.0, -90.0]])
    near_ray = np.array([0.0, 0.02, 5.0]) - centers[1]
    check = verify_by_reference_triangulation(
        identity,
        np.array([0.0, 0.0, 50.0]),  # the query at z = −50 on the same line
        np.zeros((3, 2)),
        np.arange(3, dtype=np.int64),
        np.stack([identity] * 3),
        -centers,
        np.array([[0.0, 0.0], near_ray[:2] / near_ray[2], [0.0, 0.0]]),
        np.zeros(3, np.int64),
        1e-3,
        np.full(3, 1e-3),
    )
    assert check.num_tracks == 1
    assert check.num_verified_points == 0
    assert np.isnan(check.points).all()


def _observations(setup: _Setup, query_noise_px: float = 0.0) -> list[ReferenceObservation]:
    """Each reference's matches with the query: every point, the query's pixels offset by up
    to ``query_noise_px`` (a fixed pattern)."""
    offset = query_noise_px * np.sin(np.arange(len(setup.points)))[:, None]
    return [
        ReferenceObservation(
            f"ref{i}",
            _CAMERA,
            ref,
            _pixels(setup.query, setup.points) + offset,
            _pixels(ref, setup.points),
        )
        for i, ref in enumerate(setup.references)
    ]


def test_singular_system_in_verification_is_degenerate_geometry(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    setup = _Setup()
    observations = _observations(setup)
    masks = [np.ones(len(setup.points), bool) for _ in observations]
    result = EstimateResult(setup.query, masks, 0.9, {"score": 1.0})

    def singular(*args: object) -> None:
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(verification, "check_structure", singular)
    verified = verification.verify_pose(result, _CAMERA, observations, EstimatorOptions())
    assert verified.cam_from_world is None
    assert verified.failure_reason is FailureReason.DEGENERATE_GEOMETRY
    assert verified.stats == {"score": 1.0}


def test_the_uncertainty_reads_the_check_the_verification_kept(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A verified pose carries its structure check; the uncertainty of that very pose, inliers
    and references reads it instead of checking again, and gets what a new check gives. A
    pose replaced after the verification (another object) is checked anew."""
    setup = _Setup()
    observations = _observations(setup, query_noise_px=0.3)
    masks = [np.ones(len(setup.points), bool) for _ in observations]
    options = EstimatorOptions()
    verified = verification.verify_pose(
        EstimateResult(setup.query, masks, 0.9), _CAMERA, observations, options
    )
    assert verified.structure is not None
    assert verified.stats[verification.VERIFIED_POINTS] == len(setup.points)
    fresh = pose_uncertainty(
        replace(verified, structure=None), _CAMERA, observations, options, False
    )

    calls: list[object] = []
    check_structure = verification.check_structure

    def counted(*args: Any, **kwargs: Any) -> verification.CheckedTracks | None:
        calls.append(args)
        return check_structure(*args, **kwargs)

    monkeypatch.setattr(verification, "check_structure", counted)
    kept = pose_uncertainty(verified, _CAMERA, observations, options, False)
    assert calls == []
    assert kept == fresh and kept is not None

    moved = Rigid3d(setup.query.rotation, setup.query.translation + np.array([0.01, 0.0, 0.0]))
    again = pose_uncertainty(
        replace(verified, cam_from_world=moved), _CAMERA, observations, options, False
    )
    assert len(calls) == 1
    assert again is not None and again.position_m != kept.position_m


# ---------------------------------------------------------------- pipeline on a synthetic map


class _Store:
    def __init__(self, views: list[ReferenceView], descriptors: list[NDArray[np.float32]]):
        self.views = {v.image_id: v for v in views}
        self.index = RetrievalIndex(
            [v.image_id for v in views],
            np.stack(descriptors),
            np.stack([v.cam_from_world.center for v in views]),
        )

    def retrieval_index(self) -> RetrievalIndex:
        return self.index

    def load_references(self, image_ids: list[str]) -> list[ReferenceView]:
        return [self.views[i] for i in image_ids if i in self.views]


@pytest.fixture(scope="module")
def synthetic_map() -> tuple[SyntheticScene, Localizer, _Store]:
    scene = SyntheticScene(0)
    localizer = Localizer(
        SiftExtractor(), NearestNeighborMatcher(), ThumbnailDescriptor(), 4096 * 4096
    )
    views, descriptors = [], []
    for view in scene.views(20, 1, "ref"):
        data = localizer.describe_reference(encode_png(view.image), view.camera)
        views.append(
            ReferenceView(
                view.name, view.name, view.camera, view.cam_from_world, data.features, None
            )
        )
        descriptors.append(data.global_descriptor)
    return scene, localizer, _Store(views, descriptors)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_unrelated_image_is_rejected(
    synthetic_map: tuple[SyntheticScene, Localizer, _Store], seed: int
) -> None:
    scene, localizer, store = synthetic_map
    image = encode_png(unrelated_image(seed))
    # Without any inlier-count floor, the epipolar consensus is there (what used to be
    # accepted) and only the 3D verification stands between it and a pose.
    no_floor = LocalizeParams(
        camera=scene.camera,
        options=EstimatorOptions(verification=VerificationOptions(min_inliers=0)),
    )
    result = localizer.localize(image, no_floor, store)
    assert not result.localized
    assert result.reason == FailureReason.NO_CONSENSUS.value
    assert result.cam_from_world is None
    assert sum(r.num_inliers for r in result.retrieved) >= 15  # a consensus did form
    assert result.stats["verified_points"] <= VerificationOptions().min_verified_points // 2
    defaults = localizer.localize(image, LocalizeParams(camera=scene.camera), store)
    assert not defaults.localized
    assert defaults.reason == FailureReason.NO_CONSENSUS.value


def test_true_queries_are_accepted(
    synthetic_map: tuple[SyntheticScene, Localizer, _Store],
) -> None:
    scene, localizer, store = synthetic_map
    for view in scene.views(3, 2, "query"):
        result = localizer.localize(
            encode_png(view.image), LocalizeParams(camera=view.camera), store
        )
        assert result.localized, (view.name, result.reason, result.stats)
        assert result.cam_from_world is not None
        position_error, rotation_error = pose_error(result.cam_from_world, view.cam_from_world)
        assert position_error < 0.01 * scene.extent, view.name
        assert rotation_error < 1.0, view.name
        # a wide margin over the acceptance threshold
        assert result.stats["verified_points"] >= 10 * VerificationOptions().min_verified_points
