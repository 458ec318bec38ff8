"""The sub-pixel refinement of matches: rendered views of the synthetic room, whose true
correspondences come from the query's depth and the two exact poses."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.estimators.base import ReferenceObservation
from services.features.base import LocalFeatures
from services.geometry.camera import Camera
from services.geometry.intrinsics_adaptation import rotate_points
from services.geometry.rigid import Rigid3d
from services.localization.query_frame import turn_image
from services.matching.refinement import (
    MAX_SHIFT_PX,
    RefinementImage,
    refine_reference_keypoints,
    refinement_image,
)
from services.references.images import ReferenceImageCache, reference_images
from services.references.memory import MemoryReferenceStore
from services.references.store import ReferenceData
from services.types import FloatArray, UInt8Array
from tools.synthetic.scene import SyntheticScene, encode_png


def _moved(pose: Rigid3d, shift: FloatArray, yaw_deg: float) -> Rigid3d:
    """``pose`` with its centre moved by ``shift`` (world) and turned by ``yaw_deg``."""
    turn = cv2.Rodrigues(np.array([0.0, np.radians(yaw_deg), 0.0]))[0]
    rotation = turn @ pose.rotation
    return Rigid3d(rotation, -rotation @ (pose.center + shift))


def _true_matches(
    scene: SyntheticScene, query: Rigid3d, reference: Rigid3d
) -> tuple[UInt8Array, UInt8Array, FloatArray, FloatArray]:
    """Both images and (M, 2) COLMAP keypoints of the query (corners) with where the same
    points are in the reference (visible there, away from the border)."""
    query_image, query_depth = scene.render(query)
    reference_image, reference_depth = scene.render(reference)
    gray = cv2.cvtColor(query_image, cv2.COLOR_RGB2GRAY)
    corners = cv2.goodFeaturesToTrack(gray, 400, 0.01, 8).reshape(-1, 2).astype(np.float64)
    query_xy = corners + 0.5
    cols, rows = corners.round().astype(int).T
    depth = query_depth[rows, cols].astype(np.float64)
    K = scene.camera.K
    rays = np.linalg.solve(K, np.c_[query_xy, np.ones(len(query_xy))].T).T
    points = query.inverse().apply(rays * depth[:, None])
    in_reference = reference.apply(points)
    projected = (K @ in_reference.T).T
    reference_xy = projected[:, :2] / projected[:, 2:]
    width, height = scene.camera.width, scene.camera.height
    inside = (
        (depth > 0)
        & (in_reference[:, 2] > 0)
        & (reference_xy[:, 0] > 20)
        & (reference_xy[:, 0] < width - 20)
        & (reference_xy[:, 1] > 20)
        & (reference_xy[:, 1] < height - 20)
    )
    ref_cols, ref_rows = (reference_xy[inside] - 0.5).round().astype(int).T
    seen = (
        np.abs(reference_depth[ref_rows, ref_cols] - in_reference[inside, 2])
        < 0.02 * in_reference[inside, 2]
    )
    keep = np.flatnonzero(inside)[seen]
    return query_image, reference_image, query_xy[keep], reference_xy[keep]


def _observation(
    camera: Camera, pose: Rigid3d, query_xy: FloatArray, reference_xy: FloatArray
) -> ReferenceObservation:
    return ReferenceObservation("ref", camera, pose, query_xy, reference_xy)


@pytest.fixture(scope="module")
def pair(scene: SyntheticScene) -> tuple[UInt8Array, UInt8Array, FloatArray, FloatArray]:
    query = scene.sample_pose(np.random.default_rng(7))
    return _true_matches(scene, query, _moved(query, np.array([0.3, 0.05, 0.2]), 3.0))


def _guesses(truth: FloatArray) -> FloatArray:
    """Matched keypoints as an extractor on a half-size image finds them: on its pixel grid
    (every other full pixel), up to a further pixel off."""
    rng = np.random.default_rng(0)
    return np.round(truth / 2.0) * 2.0 + rng.uniform(-1.0, 1.0, truth.shape)


class TestRefineReferenceKeypoints:
    def test_reference_keypoints_move_to_the_true_points(self, pair, scene) -> None:
        query_image, reference_image, query_xy, truth = pair
        assert len(truth) > 150
        guesses = _guesses(truth)
        size = (scene.camera.width, scene.camera.height)
        [refined] = refine_reference_keypoints(
            refinement_image(query_image, *size, 1280),
            [_observation(scene.camera, Rigid3d.identity(), query_xy, guesses)],
            lambda _: refinement_image(reference_image, *size, 1280),
        )
        before = np.linalg.norm(guesses - truth, axis=1)
        after = np.linalg.norm(refined.reference_xy - truth, axis=1)
        assert np.median(before) > 0.9
        assert np.median(after) < 0.1
        assert np.mean(after < 0.25) > 0.8
        np.testing.assert_array_equal(refined.query_xy, query_xy)  # the query side never moves

    def test_a_reference_refined_at_half_its_size_maps_back_to_full_size_pixels(
        self, pair, scene
    ) -> None:
        query_image, reference_image, query_xy, truth = pair
        width, height = scene.camera.width, scene.camera.height
        # the reference uploaded at twice the size: its keypoints are in those pixels
        large = cv2.resize(reference_image, (2 * width, 2 * height), interpolation=cv2.INTER_CUBIC)
        large_truth = truth * 2.0  # COLMAP coordinates scale about the image corner
        reference = refinement_image(large, 2 * width, 2 * height, max(width, height))
        assert reference.gray.shape == (height, width)
        [refined] = refine_reference_keypoints(
            refinement_image(query_image, width, height, max(width, height)),
            [_observation(scene.camera, Rigid3d.identity(), query_xy, _guesses(large_truth))],
            lambda _: reference,
        )
        after = np.linalg.norm(refined.reference_xy - large_truth, axis=1)
        assert np.median(after) < 0.3  # 0.15 px of the refinement image

    @pytest.mark.parametrize("turn", [90, 180, 270])
    def test_a_turned_query_is_refined_as_it_was_matched(self, pair, scene, turn: int) -> None:
        query_image, reference_image, query_xy, truth = pair
        width, height = scene.camera.width, scene.camera.height
        # the upload is the matched image turned back: its keypoints are the upload's
        upload = turn_image(query_image, (360 - turn) % 360)
        upload_xy = rotate_points(query_xy, (360 - turn) % 360, width, height)
        turned = turn_image(upload, turn)
        [refined] = refine_reference_keypoints(
            refinement_image(turned, turned.shape[1], turned.shape[0], 1280),
            [_observation(scene.camera, Rigid3d.identity(), upload_xy, _guesses(truth))],
            lambda _: refinement_image(reference_image, width, height, 1280),
            query_points=lambda xy: rotate_points(xy, turn, upload.shape[1], upload.shape[0]),
        )
        assert np.median(np.linalg.norm(refined.reference_xy - truth, axis=1)) < 0.1
        np.testing.assert_array_equal(refined.query_xy, upload_xy)

    def test_images_of_different_sizes_are_refined_on_one_canvas(self, pair, scene) -> None:
        query_image, reference_image, query_xy, truth = pair
        width, height = scene.camera.width, scene.camera.height
        # the reference's right quarter cut off (as another camera's frame): the same pixels
        # keep their coordinates, and a portrait query against a landscape reference alike
        crop = width * 3 // 4
        inside = truth[:, 0] < crop - 20
        [refined] = refine_reference_keypoints(
            refinement_image(query_image, width, height, 1280),
            [_observation(scene.camera, Rigid3d.identity(), query_xy, _guesses(truth))],
            lambda _: refinement_image(
                np.ascontiguousarray(reference_image[:, :crop]), crop, height, 1280
            ),
        )
        after = np.linalg.norm(refined.reference_xy - truth, axis=1)[inside]
        assert inside.sum() > 20 and np.median(after) < 0.1

    @pytest.mark.parametrize("larger", ["reference", "query"])
    def test_images_of_different_detail_are_aligned_at_the_coarser(
        self, pair, scene, larger: str
    ) -> None:
        """One image uploaded at twice the size holds twice the other's pixels per pixel the
        keypoints were found at (both found at 640 px): it is shrunk to the other's detail,
        so that the patches are of one scale."""
        query_image, reference_image, query_xy, truth = pair
        width, height = scene.camera.width, scene.camera.height
        query_scale, reference_scale = (1.0, 2.0) if larger == "reference" else (2.0, 1.0)

        def uploaded(image: UInt8Array, scale: float):
            size = (round(scale * width), round(scale * height))
            resized = cv2.resize(image, size, interpolation=cv2.INTER_CUBIC)
            return refinement_image(resized, *size, 1280)

        query = uploaded(query_image, query_scale)
        reference = uploaded(reference_image, reference_scale)
        assert max(query.detail, reference.detail) == pytest.approx(
            2 * min(query.detail, reference.detail)
        )
        reference_truth = truth * reference_scale  # COLMAP coordinates scale about the corner
        [refined] = refine_reference_keypoints(
            query,
            [
                _observation(
                    scene.camera,
                    Rigid3d.identity(),
                    query_xy * query_scale,
                    _guesses(reference_truth),
                )
            ],
            lambda _: reference,
        )
        after = np.linalg.norm(refined.reference_xy - reference_truth, axis=1) / reference_scale
        assert np.median(after) < 0.15  # in pixels of the image the keypoints were found on

    def test_keypoints_that_cannot_be_aligned_keep_their_match(self, pair, scene) -> None:
        query_image, reference_image, query_xy, truth = pair
        size = (scene.camera.width, scene.camera.height)
        far = truth + 3 * MAX_SHIFT_PX  # a wrong match, far from the point
        flat = np.zeros_like(reference_image)  # nothing to align to
        query = refinement_image(query_image, *size, 1280)
        for reference, guesses in ((reference_image, far), (flat, _guesses(truth))):
            [refined] = refine_reference_keypoints(
                query,
                [_observation(scene.camera, Rigid3d.identity(), query_xy, guesses)],
                lambda _, image=reference: refinement_image(image, *size, 1280),
            )
            moved = np.linalg.norm(refined.reference_xy - guesses, axis=1)
            assert np.all((moved == 0) | (moved < MAX_SHIFT_PX))
            if reference is flat:  # LK rarely reports a patch found in a blank image
                assert np.mean(moved == 0) > 0.95
        assert np.mean(np.linalg.norm(refined.reference_xy - truth, axis=1) < 0.25) < 0.5

    def test_without_an_image_or_time_left_matches_stay(self, pair, scene) -> None:
        query_image, reference_image, query_xy, truth = pair
        size = (scene.camera.width, scene.camera.height)
        observation = _observation(scene.camera, Rigid3d.identity(), query_xy, _guesses(truth))
        query = refinement_image(query_image, *size, 1280)
        reference = refinement_image(reference_image, *size, 1280)
        assert refine_reference_keypoints(query, [observation], lambda _: None) == [observation]
        assert refine_reference_keypoints(
            query, [observation], lambda _: reference, stop=lambda: True
        ) == [observation]


def _described(scene: SyntheticScene) -> ReferenceData:
    """A reference's stored description (no keypoints: only its original matters here)."""
    features = LocalFeatures(
        np.zeros((0, 2), np.float32),
        np.zeros((0, 128), np.float32),
        np.zeros(0, np.float32),
        (scene.camera.width, scene.camera.height),
    )
    return ReferenceData(features, np.zeros(4, np.float32), None, "sift", "thumb")


class TestReferenceImages:
    def test_originals_are_decoded_once_at_the_refinement_size_and_kept(self, scene) -> None:
        view_image, _ = scene.render(scene.sample_pose(np.random.default_rng(3)))
        reads: list[str] = []

        def original(image_id: str) -> bytes:
            reads.append(image_id)
            return encode_png(view_image)

        store = MemoryReferenceStore(original)
        data = _described(scene)
        store.add("a.png", scene.camera, Rigid3d.identity(), data, "a")
        store.add("b.png", scene.camera, Rigid3d.identity(), data, "b")
        views = store.load_references(["a", "b"])
        one = RefinementImage(np.zeros((240, 320), np.uint8), 640, 480, 320).nbytes
        cache = ReferenceImageCache(one + one // 2)  # room for one image at 320 px
        image = reference_images(store, views, 320, 40_000_000, cache)
        first = image("a")
        assert first is not None and first.gray.shape == (240, 320)
        assert first.scale == (0.5, 0.5)
        assert image("a") is first and reads == ["a"]
        assert image("b") is not None and reads == ["a", "b"]
        assert cache.bytes == one  # "a" made room for "b"
        assert image("a") is not first and reads == ["a", "b", "a"]
        assert image("unknown") is None

    def test_a_store_without_originals_gives_no_images(self, scene) -> None:
        store = MemoryReferenceStore()
        data = _described(scene)
        store.add("a.png", scene.camera, Rigid3d.identity(), data, "a")
        views = store.load_references(["a"])
        assert views[0].original_key is None
        assert (
            reference_images(store, views, 320, 40_000_000, ReferenceImageCache(2**20))("a") is None
        )
