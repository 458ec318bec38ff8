"""Localize refines its matches on the references' originals from the blob store, on SQLite and
PostgreSQL, and answers as well without them."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.geometry.rigid import Rigid3d, pose_error
from services.localization.localizer import Localizer
from services.references.images import ReferenceImageCache
from tests.api.test_localize_frames import _alignment_error, _localize
from tests.conftest import localize_view, make_client, upload_view
from tools.synthetic.scene import SyntheticScene, SyntheticView, encode_png


@pytest.fixture
def cache() -> ReferenceImageCache:
    return ReferenceImageCache(64 * 2**20)


@pytest.fixture
def refining(
    database_url: str, localizer: Localizer, cache: ReferenceImageCache
) -> Iterator[TestClient]:
    """A server whose configuration refines its matches (as the xfeat family's does)."""
    engine = Localizer(
        localizer.extractor,
        localizer.matcher,
        localizer.global_descriptor,
        localizer.max_pixels,
        reference_images=cache,
    )
    with make_client(database_url, engine) as client:
        yield client


def _error(answer: dict[str, object], view: SyntheticView) -> tuple[float, float]:
    pose = answer["cam_from_world"]
    assert isinstance(pose, dict)
    estimate = Rigid3d.from_quaternion(np.array(pose["rotation"]), np.array(pose["translation"]))
    return pose_error(estimate, view.cam_from_world)


def _map_of(client: TestClient, views: list[SyntheticView]) -> str:
    map_id = client.post("/v1/maps", json={"name": "refined"}).json()["id"]
    for view in views:
        assert upload_view(client, map_id, view).status_code == 201
    return str(map_id)


def test_matches_are_refined_on_the_originals(
    refining: TestClient,
    cache: ReferenceImageCache,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    map_id = _map_of(refining, reference_views[:12])
    query = query_views[0]
    answer = localize_view(refining, map_id, query).json()
    assert answer["localized"], answer
    position, rotation = _error(answer, query)
    assert position < 0.02 and rotation < 0.2
    assert cache.bytes > 0  # the retrieved references' originals were read and decoded


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
    assert _error(answer, query)[0] < 0.05
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
