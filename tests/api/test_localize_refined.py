"""Localize refines its matches on the references' originals from the blob store, on SQLite and
PostgreSQL, and answers as well without them."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.features.base import LocalFeatures
from services.geometry.intrinsics_adaptation import rotated_from_camera
from services.geometry.rigid import Rigid3d, pose_error
from services.localization import localizer as localizer_module
from services.localization.localizer import Localizer
from services.matching.refinement import refine_reference_keypoints
from services.references.images import ReferenceImageCache
from tests.api.test_ar_localize import post, sensor_camera
from tests.api.test_localize_frames import _alignment_error, _localize
from tests.conftest import localize_view, make_client, upload_view
from tools.synthetic.scene import SyntheticScene, SyntheticView, encode_jpeg, encode_png


@pytest.fixture
def cache() -> ReferenceImageCache:
    return ReferenceImageCache(64 * 2**20)


class _OnAHalfSizeGrid:
    """The session's extractor with its keypoints moved to the pixel grid of the image at half
    size, as an extractor that detects on a shrunken image finds them (XFeat's)."""

    def __init__(self, extractor: Any) -> None:
        self.extractor = extractor

    def extract(self, image: Any, spare: Any = None) -> LocalFeatures:
        features: LocalFeatures = self.extractor.extract(image, spare)
        return replace(features, keypoints=np.round(features.keypoints / 2.0) * 2.0)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.extractor, name)


def _server(url: str, localizer: Localizer, cache: ReferenceImageCache | None) -> TestClient:
    engine = Localizer(
        _OnAHalfSizeGrid(localizer.extractor),  # type: ignore[arg-type]
        localizer.matcher,
        localizer.global_descriptor,
        localizer.max_pixels,
        reference_images=cache,
    )
    return make_client(url, engine)


@pytest.fixture
def refining(
    database_url: str, localizer: Localizer, cache: ReferenceImageCache
) -> Iterator[TestClient]:
    """A server whose configuration refines its matches (as the xfeat family's does)."""
    with _server(database_url, localizer, cache) as client:
        yield client


def _error(answer: dict[str, object], truth: Rigid3d) -> tuple[float, float]:
    pose = answer["cam_from_world"]
    assert isinstance(pose, dict)
    estimate = Rigid3d.from_quaternion(np.array(pose["rotation"]), np.array(pose["translation"]))
    return pose_error(estimate, truth)


def _map_of(client: TestClient, views: list[SyntheticView]) -> str:
    map_id = client.post("/v1/maps", json={"name": "refined"}).json()["id"]
    for view in views:
        assert upload_view(client, map_id, view).status_code == 201
    return str(map_id)


def _shifts(monkeypatch: pytest.MonkeyPatch) -> list[np.ndarray]:
    """Where each refinement's shifts of the reference keypoints (px) are recorded."""
    shifts: list[np.ndarray] = []

    def recorded(query: Any, observations: Any, *args: Any, **kwargs: Any) -> Any:
        refined = refine_reference_keypoints(query, observations, *args, **kwargs)
        for before, after in zip(observations, refined, strict=True):
            shifts.append(np.linalg.norm(after.reference_xy - before.reference_xy, axis=1))
        return refined

    monkeypatch.setattr(localizer_module, "refine_reference_keypoints", recorded)
    return shifts


def test_matches_are_refined_on_the_originals(
    refining: TestClient,
    cache: ReferenceImageCache,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    map_id = _map_of(refining, reference_views[:12])
    shifts = _shifts(monkeypatch)
    query = query_views[0]
    answer = localize_view(refining, map_id, query).json()
    assert answer["localized"], answer
    position, rotation = _error(answer, query.cam_from_world)
    assert position < 0.02 and rotation < 0.2
    assert cache.bytes > 0  # the retrieved references' originals were read and decoded
    moved = np.concatenate(shifts)  # most keypoints back from the half-size grid
    assert np.mean((moved > 0) & (moved <= 1.5)) > 0.3


def test_references_whose_originals_are_gone_keep_their_matches(
    refining: TestClient,
    cache: ReferenceImageCache,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    map_id = _map_of(refining, reference_views[:12])
    blobs = refining.app.state.blobs  # type: ignore[attr-defined]
    for blob in list(blobs.list()):  # a blob store that lost them
        blobs.delete(blob.key)
    query = query_views[0]
    answer = localize_view(refining, map_id, query).json()
    assert answer["localized"], answer
    assert _error(answer, query.cam_from_world)[0] < 0.05
    assert cache.bytes == 0


def test_each_frame_of_a_multi_frame_query_is_refined(
    refining: TestClient,
    cache: ReferenceImageCache,
    reference_views: list[SyntheticView],
    scene: SyntheticScene,
) -> None:
    map_id = _map_of(refining, reference_views[:12])
    frames = scene.views(3, stream=7, prefix="frame")
    result = _localize(refining, map_id, frames, [encode_png(v.image) for v in frames])
    assert result["localized"], result
    position, rotation = _alignment_error(result)
    assert position < 0.02 and rotation < 0.2
    assert cache.bytes > 0


def test_a_portrait_upload_is_refined_turned_upright(
    refining: TestClient,
    cache: ReferenceImageCache,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The query is matched turned upright; its keypoints go back to the upload, and the
    refinement aligns its patches turned as they were matched: most reference keypoints move
    back from the half-size grid (by at most 1.5 px), as they do for an upright query."""
    map_id = _map_of(refining, reference_views[:12])
    shifts = _shifts(monkeypatch)
    view = query_views[0]
    portrait = np.ascontiguousarray(np.rot90(view.image, k=-1))
    turn = rotated_from_camera(90)
    truth = Rigid3d(turn @ view.cam_from_world.rotation, turn @ view.cam_from_world.translation)
    down = (view.cam_from_world.rotation @ [0.0, 1.0, 0.0]).tolist()
    params = {"camera": sensor_camera(view), "gravity": {"down": down, "map_down": [0, 1, 0]}}
    response = post(refining, map_id, encode_jpeg(portrait), params)
    answer = response.json()  # type: ignore[attr-defined]
    assert answer["localized"], answer
    assert answer["upright_turn_deg"] == 270
    position, rotation = _error(answer, truth)
    assert position < 0.02 and rotation < 0.2
    moved = np.concatenate(shifts)
    assert np.mean((moved > 0) & (moved <= 1.5)) > 0.3  # 0.57 here; 0.0002 when not turned


def test_a_portrait_upload_searched_without_gravity_is_answered(
    refining: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    """Without gravity the upload is matched as it comes, portrait against landscape
    references: images of two shapes are refined together."""
    map_id = _map_of(refining, reference_views[:12])
    view = query_views[0]
    portrait = np.ascontiguousarray(np.rot90(view.image, k=-1))
    response = post(refining, map_id, encode_jpeg(portrait), {"camera": sensor_camera(view)})
    assert response.status_code == 200, response.text  # type: ignore[attr-defined]
    answer = response.json()  # type: ignore[attr-defined]
    assert answer["localized"], answer


def test_a_query_of_another_resolution_is_refined(
    refining: TestClient,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A query at 1.5 times the references' resolution, both under the extraction's longer
    side (found at full size: the same detail): refined against references of another size."""
    map_id = _map_of(refining, reference_views[:12])
    shifts = _shifts(monkeypatch)
    view = query_views[0]
    width, height = 3 * view.camera.width // 2, 3 * view.camera.height // 2
    image = cv2.resize(view.image, (width, height), interpolation=cv2.INTER_CUBIC)
    camera = sensor_camera(view, factor=1)
    camera.update(width=width, height=height, params=[1.5 * p for p in view.camera.params])
    response = post(refining, map_id, encode_jpeg(image), {"camera": camera})
    assert response.status_code == 200, response.text  # type: ignore[attr-defined]
    answer = response.json()  # type: ignore[attr-defined]
    assert answer["localized"], answer
    assert _error(answer, view.cam_from_world)[0] < 0.02
    moved = np.concatenate(shifts)
    assert np.mean(moved > 0) > 0.3
