"""JPEGs far larger than the extractor's working size are decoded at 1/2, 1/4 or 1/8 scale
(issue 14): keypoints still come back in full-size COLMAP pixels and poses stay exact, checked
on the synthetic scene rendered at 640×480 and upscaled ×4 as JPEG."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.features.base import FeatureExtractor, LocalFeatures
from services.geometry.camera import Camera
from services.geometry.rigid import pose_error
from services.imaging.decode import decode_image_reduced
from services.localization.localizer import LocalizeParams, Localizer
from services.references.memory import MemoryReferenceStore
from services.runtime.spare_workers import SpareWorkers
from services.types import UInt8Array
from tools.synthetic.scene import SyntheticScene, SyntheticView, encode_png

UPSCALE = 4


def upscaled_jpeg(image: UInt8Array, k: int = UPSCALE) -> bytes:
    """``image`` enlarged ``k`` times (pixel-centre aligned, as COLMAP scales about the corner)
    and encoded as a JPEG."""
    height, width = image.shape[:2]
    big = cv2.resize(image, (width * k, height * k), interpolation=cv2.INTER_CUBIC)
    ok, data = cv2.imencode(
        ".jpg", cv2.cvtColor(big, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95]
    )
    assert ok
    return data.tobytes()


def upscaled_camera(camera: Camera, k: int = UPSCALE) -> Camera:
    """The intrinsics of the image enlarged ``k`` times (pinhole models: every parameter is
    in pixels)."""
    assert camera.model in ("PINHOLE", "SIMPLE_PINHOLE")
    return Camera(
        camera.model, camera.width * k, camera.height * k, tuple(p * k for p in camera.params)
    )


class RecordingExtractor:
    """An extractor that remembers the size of every image it was given."""

    def __init__(self, inner: FeatureExtractor) -> None:
        self.inner = inner
        self.name = inner.name
        self.max_side = inner.max_side
        self.rotation_invariant = inner.rotation_invariant
        self.sizes: list[tuple[int, int]] = []

    def extract(self, image: UInt8Array, spare: SpareWorkers | None = None) -> LocalFeatures:
        self.sizes.append((image.shape[1], image.shape[0]))
        return self.inner.extract(image, spare)

    def with_budget(self, max_keypoints: int | None, max_side: int | None) -> FeatureExtractor:
        return RecordingExtractor(self.inner.with_budget(max_keypoints, max_side))


def recording(localizer: Localizer, max_side: int) -> tuple[Localizer, RecordingExtractor]:
    extractor = RecordingExtractor(localizer.extractor.with_budget(None, max_side))
    return (
        Localizer(extractor, localizer.matcher, localizer.global_descriptor, localizer.max_pixels),
        extractor,
    )


@pytest.mark.parametrize(
    ("min_side", "factor"), [(None, 1), (3000, 1), (1280, 2), (1024, 2), (640, 4), (320, 8)]
)
def test_jpeg_decoded_at_the_smallest_scale_that_keeps_min_side(
    min_side: int | None, factor: int, scene: SyntheticScene, reference_views: list[SyntheticView]
) -> None:
    data = upscaled_jpeg(reference_views[0].image)  # 2560×1920
    decoded = decode_image_reduced(data, 40_000_000, min_side)
    assert (decoded.width, decoded.height, decoded.factor) == (2560, 1920, factor)
    assert decoded.rgb.shape == (1920 // factor, 2560 // factor, 3)
    if factor > 1:  # the reduced image is the full one averaged over factor × factor blocks
        full = decode_image_reduced(data, 40_000_000, None).rgb.astype(np.float32)
        averaged = cv2.resize(full, (2560 // factor, 1920 // factor), interpolation=cv2.INTER_AREA)
        assert np.abs(averaged - decoded.rgb).mean() < 2.0


def test_odd_size_and_png_decode() -> None:
    """A size that is no multiple of the factor rounds up as libjpeg does; a PNG is always
    decoded in full."""
    image = np.random.default_rng(0).integers(0, 255, (1921, 2563, 3), dtype=np.uint8)
    ok, jpeg = cv2.imencode(".jpg", image)
    assert ok
    decoded = decode_image_reduced(jpeg.tobytes(), 40_000_000, 640)
    assert (decoded.width, decoded.height, decoded.factor) == (2563, 1921, 4)
    assert decoded.rgb.shape == (481, 641, 3)
    png = decode_image_reduced(encode_png(image), 40_000_000, 640)
    assert (png.width, png.height, png.factor, png.rgb.shape) == (2563, 1921, 1, (1921, 2563, 3))


@pytest.mark.parametrize(("max_side", "factor"), [(1024, 2), (640, 4)])
def test_reference_keypoints_in_full_size_pixels(
    max_side: int, factor: int, localizer: Localizer, reference_views: list[SyntheticView]
) -> None:
    """The ×4 JPEG of a reference is described from a reduced decode; its keypoints are the
    640×480 image's keypoints times 4 (to within half a working pixel)."""
    view = reference_views[0]
    small = localizer.for_map(None, max_side).describe_reference(
        encode_png(view.image), view.camera
    )
    recorder_localizer, recorder = recording(localizer, max_side)
    big = recorder_localizer.describe_reference(
        upscaled_jpeg(view.image), upscaled_camera(view.camera)
    )
    assert recorder.sizes == [(2560 // factor, 1920 // factor)]
    assert big.features.image_size == (2560, 1920)
    kp = big.features.keypoints
    assert len(kp) > 200
    assert (kp >= 0).all() and (kp[:, 0] <= 2560).all() and (kp[:, 1] <= 1920).all()
    # each ×4 keypoint's nearest 640×480 keypoint (scaled ×4)
    distance = np.linalg.norm(kp[:, None] - UPSCALE * small.features.keypoints[None], axis=2)
    nearest = distance.min(axis=1)
    assert np.median(nearest) < 0.5 * UPSCALE, np.median(nearest)


@pytest.mark.parametrize("max_side", [1024, 640])
def test_upscaled_queries_and_references_localize_exactly(
    max_side: int,
    localizer: Localizer,
    scene: SyntheticScene,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    """References and queries as ×4 JPEGs with ×4 intrinsics: poses as accurate as the
    640×480 pipeline's (tests/engine/test_pipeline_estimators.py). The references are decoded
    reduced; a single-image query is decoded in full (the upright-turn search's image)."""
    big_localizer, recorder = recording(localizer, max_side)
    store = MemoryReferenceStore()
    for view in reference_views:
        data = big_localizer.describe_reference(
            upscaled_jpeg(view.image), upscaled_camera(view.camera)
        )
        store.add(view.name, upscaled_camera(view.camera), view.cam_from_world, data)
    assert all(max_side <= max(size) < 2 * max_side for size in recorder.sizes)
    for view in query_views[:3]:
        result = big_localizer.localize(
            upscaled_jpeg(view.image), LocalizeParams(camera=upscaled_camera(view.camera)), store
        )
        assert result.localized, (view.name, result.reason)
        assert result.cam_from_world is not None
        dt, dr = pose_error(result.cam_from_world, view.cam_from_world)
        assert dt < 0.01 * scene.extent and dr < 0.5, (view.name, dt, dr)
