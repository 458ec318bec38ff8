"""The thread policy in /v1/health and the reference-feature cache against real databases:
hits skip the decode, deletes are never served from it (issue #13)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

import db.store
from app.engine_config import service_memory_bound
from app.usecases.images import delete_image
from app.usecases.localize import reference_store
from services.localization.localizer import Localizer
from services.references.cache import ReferenceFeatureCache
from services.runtime.threads import usable_cores
from services.runtime.worker_slots import WorkerSlots
from tests.conftest import create_map, localize_view, make_client, upload_view
from tools.synthetic.scene import SyntheticView, encode_png


@pytest.fixture(autouse=True)
def _restore_opencv_threads() -> Iterator[None]:
    """The app's lifespan sets OpenCV's threads for the whole process."""
    before = cv2.getNumThreads()
    yield
    cv2.setNumThreads(before)


@pytest.mark.parametrize(
    ("settings", "expected"),
    [
        ({"cpu_cores": 4, "localize_workers": 1}, (4, 1, 4)),
        ({"cpu_cores": 2}, (2, 2, 1)),
        ({"cpu_cores": 8, "onnx_threads": 2}, (8, 4, 2)),
        ({}, (usable_cores(), min(usable_cores(), 4), max(1, usable_cores() // 4))),
    ],
)
def test_health_reports_the_thread_policy(
    tmp_path: Path,
    localizer: Localizer,
    settings: dict[str, int],
    expected: tuple[int, int, int],
) -> None:
    url = f"sqlite:///{tmp_path / 'slloc.db'}"
    with make_client(url, localizer, reference_cache_mib=64, **settings) as c:
        runtime = c.get("/v1/health").json()["runtime"]
        assert (
            runtime["cores"],
            runtime["localize_workers"],
            runtime["threads_per_worker"],
        ) == expected
        assert runtime["reference_cache_mib"] == 64 and runtime["reference_cache_used_mib"] == 0
        assert cv2.getNumThreads() == expected[2]
        assert c.app.state.admission.slots.semaphore._value == expected[1]  # type: ignore[attr-defined]
        assert runtime["idle_workers_lent"] == expected[1] - 1


@pytest.fixture
def small_map(client: TestClient, reference_views: list[SyntheticView]) -> tuple[str, list[str]]:
    """A map of four references and their ids."""
    map_id = create_map(client)
    ids = []
    for view in reference_views[:4]:
        response = upload_view(client, map_id, view)
        assert response.status_code == 201, response.text  # type: ignore[attr-defined]
        ids.append(response.json()["id"])  # type: ignore[attr-defined]
    return map_id, ids


@pytest.fixture
def decodes(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The kinds of the feature arrays the store decodes, in order."""
    seen: list[str] = []
    original = db.store.from_row

    def counting(row: db.store.FeatureArray) -> np.ndarray:
        seen.append(row.kind)
        return original(row)

    monkeypatch.setattr(db.store, "from_row", counting)
    return seen


def test_a_cached_reference_is_not_decoded_again(
    client: TestClient, localizer: Localizer, small_map: tuple[str, list[str]], decodes: list[str]
) -> None:
    map_id, ids = small_map
    cache: ReferenceFeatureCache = client.app.state.reference_cache  # type: ignore[attr-defined]
    store = reference_store(
        client.app.state.sessions,  # type: ignore[attr-defined]
        map_id,
        localizer,
        features_cache=cache,
    )
    first = store.load_references(ids[:2])
    assert {"keypoints", "descriptors", "scores"} <= set(decodes)
    decodes.clear()
    again = store.load_references(ids)  # two hits, two misses
    assert [v.image_id for v in again] == ids
    assert sorted(decodes) == sorted(["keypoints", "descriptors", "scores"] * 2)
    for old, new in zip(first, again[:2], strict=True):
        assert new.features.descriptors is old.features.descriptors
    decodes.clear()
    assert [v.image_id for v in store.load_references(ids[::-1])] == ids[::-1]
    assert decodes == []
    stats = cache.stats()
    assert stats.entries == 4 and stats.hits >= 6
    used = client.get("/v1/health").json()["runtime"]["reference_cache_used_mib"]
    assert used == pytest.approx(stats.bytes / 2**20, abs=1e-3) and used > 0


def test_a_deleted_reference_is_never_served_from_the_cache(
    client: TestClient, localizer: Localizer, small_map: tuple[str, list[str]]
) -> None:
    map_id, ids = small_map
    sessions = client.app.state.sessions  # type: ignore[attr-defined]
    cache: ReferenceFeatureCache = client.app.state.reference_cache  # type: ignore[attr-defined]
    store = reference_store(sessions, map_id, localizer, features_cache=cache)
    assert len(store.load_references(ids)) == 4 and cache.stats().entries == 4

    # through the API: the entry goes with the image
    assert client.delete(f"/v1/maps/{map_id}/images/{ids[0]}").status_code == 204
    assert cache.get(map_id, ids[0]) is None
    assert [v.image_id for v in store.load_references(ids)] == ids[1:]

    # by another process (no access to this cache): the entry stays but is not served
    delete_image(sessions, map_id, ids[1])
    assert cache.get(map_id, ids[1]) is not None
    assert [v.image_id for v in store.load_references(ids)] == ids[2:]

    # the whole map
    assert client.delete(f"/v1/maps/{map_id}").status_code == 204
    assert all(cache.get(map_id, i) is None for i in ids)
    assert store.load_references(ids) == []


def test_the_cache_bound_holds_while_localizing(
    database_url: str,
    localizer: Localizer,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    with make_client(database_url, localizer, reference_cache_mib=1) as c:
        map_id = create_map(c)
        for view in reference_views[:8]:
            assert upload_view(c, map_id, view).status_code == 201  # type: ignore[attr-defined]
        cache: ReferenceFeatureCache = c.app.state.reference_cache  # type: ignore[attr-defined]
        for view in query_views[:3]:
            response = c.post(
                f"/v1/maps/{map_id}/localize",
                files={"image": ("q.png", encode_png(view.image), "image/png")},
            )
            assert response.status_code == 200, response.text
            stats = cache.stats()
            assert 0 < stats.bytes <= 2**20 and stats.entries >= 1


def test_health_reports_the_memory_bound(tmp_path: Path, localizer: Localizer) -> None:
    """The bound's terms in /v1/health are the settings' (services/runtime/memory.py), their
    sum is the bound, and a smaller setting gives a smaller bound."""
    url = f"sqlite:///{tmp_path / 'slloc.db'}"
    bounds = []
    for max_top_k in (50, 10):
        # the served extractor's terms alone; its largest request peaks while it matches
        settings = {
            "cpu_cores": 2,
            "localize_workers": 2,
            "max_top_k": max_top_k,
            "evaluation_features": "",
        }
        with make_client(url, localizer, **settings) as c:
            runtime = c.get("/v1/health").json()["runtime"]
            state = c.app.state  # type: ignore[attr-defined]
            expected = service_memory_bound(state.settings, state.engine_config)
        terms = runtime["memory_terms_mib"]
        assert terms.pop("retrieval_index") == 0  # nothing localized yet
        assert terms == pytest.approx(expected.terms)
        assert runtime["memory_bound_mib"] == pytest.approx(expected.total_mib, abs=0.1)
        bounds.append(runtime["memory_bound_mib"])
    assert bounds[1] < bounds[0]


def test_health_counts_the_retrieval_indexes(
    client: TestClient, small_map: tuple[str, list[str]], query_views: list[SyntheticView]
) -> None:
    map_id, _ = small_map
    response = client.post(
        f"/v1/maps/{map_id}/localize",
        files={"image": ("q.png", encode_png(query_views[0].image), "image/png")},
    )
    assert response.status_code == 200, response.text
    runtime = client.get("/v1/health").json()["runtime"]
    index_mib = runtime["memory_terms_mib"]["retrieval_index"]
    assert index_mib > 0
    assert runtime["memory_bound_mib"] == pytest.approx(
        sum(runtime["memory_terms_mib"].values()), abs=0.1
    )


class _RecordingSlots(WorkerSlots):
    """Worker slots that record each reservation and the memory held while it runs."""

    def __init__(self, workers: int, memory_mib: float) -> None:
        super().__init__(workers, memory_mib)
        self.reserved: list[float] = []
        self.held: list[float] = []

    @contextmanager
    def hold(self, mib: float) -> Iterator[None]:
        with super().hold(mib):
            self.reserved.append(mib)
            self.held.append(self.held_mib)
            yield


def test_requests_compute_within_the_memory_their_shape_needs(
    client: TestClient,
    small_map: tuple[str, list[str]],
    query_views: list[SyntheticView],
    reference_views: list[SyntheticView],
    localizer: Localizer,
) -> None:
    """A localize reserves the largest of its image's stages, its matching of its top_k
    references' features included, out of the bound's computing term; an add reserves no
    matching (on these small images both peak while they extract); both give it back when
    they answer."""
    map_id, _ = small_map
    state = client.app.state  # type: ignore[attr-defined]
    computing = state.memory_bound.terms["computing"]
    original = state.admission.slots
    state.admission.slots = slots = _RecordingSlots(original.workers, computing)
    try:
        view = query_views[0]
        assert localize_view(client, map_id, view).status_code == 200
        added = upload_view(client, map_id, reference_views[5], name="added")
        assert added.status_code == 201, added.text  # type: ignore[attr-defined]
        runtime = client.get("/v1/health").json()["runtime"]
    finally:
        state.admission.slots = original
    height, width = view.image.shape[:2]
    assert slots.reserved == [
        pytest.approx(localizer.memory_mib(width, height, False, 10)),  # top_k's default
        pytest.approx(localizer.memory_mib(width, height, False)),
    ]
    assert slots.held == slots.reserved  # each computed alone, holding its own share
    assert 0 < slots.reserved[1] <= slots.reserved[0] < computing
    assert runtime["computing_memory_held_mib"] == 0
