"""The approximate retrieval index against exact search: recall, the position prior, deletes,
and the retrieval cache switching to it above the configured size, building it in the
background while adds and deletes go on."""

from __future__ import annotations

import threading
from dataclasses import replace

import numpy as np
import pytest

from services.retrieval.ann import AnnOptions, AnnView
from services.retrieval.cache import RetrievalIndexCache
from services.retrieval.contracts import RetrievalIndex, VocabularyState
from services.retrieval.search import PositionPrior, search_index, top_k
from services.retrieval.training import BackgroundTrainer
from tools.synthetic.descriptors import place_views, unit_rows

DIM = 1024  # the service's VLAD length (8 centres × 128-D ALIKED descriptors)


PLACES = unit_rows(np.random.default_rng(10), 400, DIM)  # 50 references per place


def queries_of(rng: np.random.Generator, n: int) -> np.ndarray:
    """New views of random places: their exact top-10 are views of the same place."""
    return place_views(rng, PLACES, rng.integers(0, len(PLACES), n))


@pytest.fixture(scope="module")
def scene() -> RetrievalIndex:
    rng = np.random.default_rng(0)
    vectors = place_views(rng, PLACES, rng.integers(0, len(PLACES), 20_000))
    centers = rng.uniform(-100, 100, (20_000, 3))
    return RetrievalIndex([f"r{i}" for i in range(20_000)], vectors, centers)


@pytest.fixture(scope="module")
def approximate(scene: RetrievalIndex) -> RetrievalIndex:
    """``scene`` searched through a faiss index (1000 references and up)."""
    return replace(scene, ann=AnnView.build(scene.descriptors, AnnOptions(1000, nprobe=16)))


def recall_at_10(index: RetrievalIndex, queries: np.ndarray, prior: PositionPrior | None) -> float:
    hits = 0
    for query in queries:
        exact, _ = top_k(query, index.descriptors, 10, index.centers, prior)
        approx, _ = search_index(index, query, 10, prior)
        hits += len(set(exact.tolist()) & set(approx.tolist()))
    return hits / (10 * len(queries))


def test_recall_against_exact_search(approximate: RetrievalIndex) -> None:
    rng = np.random.default_rng(1)
    index = approximate
    queries = queries_of(rng, 50)
    assert recall_at_10(index, queries, None) >= 0.95
    rows, scores = search_index(index, queries[0], 10)
    assert rows.shape == (10,) and np.all(np.diff(scores) <= 1e-6)  # best first
    exact_scores = index.descriptors[rows] @ queries[0]
    np.testing.assert_allclose(scores, exact_scores, rtol=1e-6)  # rescored exactly


def test_prior_is_respected(approximate: RetrievalIndex) -> None:
    """A prior holding more references than ``min_references`` goes through faiss with an id
    filter; every answer lies inside it."""
    rng = np.random.default_rng(2)
    index = approximate
    prior = PositionPrior(np.zeros(3), 60.0, up=np.array([0.0, 0.0, 1.0]))
    inside = prior.distances(index.centers) <= prior.radius
    assert 1000 < inside.sum() < 20_000
    outside_rows = np.flatnonzero(~inside)
    queries = np.concatenate([queries_of(rng, 20), index.descriptors[outside_rows[:10]]])
    for query in queries:
        rows, _ = search_index(index, query, 10, prior)
        assert rows.size == 10 and inside[rows].all()
    assert recall_at_10(index, queries, prior) >= 0.9


def test_deletes_and_adds_are_respected(scene: RetrievalIndex) -> None:
    view = AnnView.build(scene.descriptors[:10_000], AnnOptions(1000, nprobe=16))
    stale_index = RetrievalIndex(
        scene.image_ids[:10_000], scene.descriptors[:10_000], scene.centers[:10_000], ann=view
    )
    keep = np.arange(0, 10_000, 2)  # delete every odd row
    added = scene.descriptors[10_000:12_000]
    updated = view.updated(
        np.concatenate([keep, np.full(2000, -1)]), np.concatenate([scene.descriptors[keep], added])
    )
    index = RetrievalIndex(
        [scene.image_ids[i] for i in keep] + scene.image_ids[10_000:12_000],
        np.concatenate([scene.descriptors[keep], added]),
        np.concatenate([scene.centers[keep], scene.centers[10_000:12_000]]),
        ann=updated,
    )
    assert updated.index.ntotal == 7_000
    for row in range(1, 40, 2):  # a deleted vector is gone from faiss itself
        slots, _ = updated.index.search(scene.descriptors[row], 10)
        assert slots.size == 10 and row not in slots.tolist()
        rows, _ = search_index(index, scene.descriptors[row], 10)
        assert f"r{row}" not in {index.image_ids[r] for r in rows}
    for i, query in enumerate(added[:20]):  # an added one is found by its own vector
        rows, _ = search_index(index, query, 1)
        assert index.image_ids[rows[0]] == f"r{10_000 + i}"
    # the snapshot from before the update maps only its own rows (new slots are skipped)
    rows, _ = search_index(stale_index, added[0], 10)
    assert np.all(rows < 10_000) and np.all(rows % 2 == 0)


class _Source:
    """An ``IndexSource`` over arrays held in memory."""

    map_id = "m"
    feature_model = "aliked"
    descriptor_model = "global"

    def __init__(self, vectors: np.ndarray) -> None:
        self.vectors = {f"r{i}": v for i, v in enumerate(vectors)}
        self.rev = 1

    def revision(self) -> int | None:
        return self.rev

    def reference_ids(self) -> list[str]:
        return list(self.vectors)

    def vocabulary(self) -> VocabularyState | None:
        return None

    def load_index(
        self, vocabulary: VocabularyState | None, only_ids: list[str] | None = None
    ) -> RetrievalIndex:
        ids = sorted(self.vectors if only_ids is None else only_ids)
        return RetrievalIndex(
            ids, np.stack([self.vectors[i] for i in ids]), np.zeros((len(ids), 3))
        )


def test_cache_uses_the_approximate_index_above_the_threshold(scene: RetrievalIndex) -> None:
    source = _Source(scene.descriptors[:3000])
    cache = RetrievalIndexCache(AnnOptions(min_references=2000, nprobe=16))
    index = cache.index(source)
    assert index.ann is not None and index.ann.index.ntotal == 3000
    for i in range(1500):  # below the threshold: exact search again
        del source.vectors[f"r{i}"]
    source.rev = 2
    index = cache.index(source)
    assert index.ann is None and len(index.image_ids) == 1500
    source.vectors.update({f"r{i}": scene.descriptors[i] for i in range(3000, 4000)})
    source.rev = 3
    index = cache.index(source)
    assert index.ann is not None and index.ann.index.ntotal == 2500
    del source.vectors["r3500"]
    source.rev = 4
    index = cache.index(source)
    assert index.ann is not None and index.ann.index.ntotal == 2499
    rows, _ = search_index(index, scene.descriptors[3500], 10)
    assert "r3500" not in {index.image_ids[r] for r in rows}
    assert cache.size().nbytes > index.descriptors.nbytes


def test_background_build_catches_up_with_changes_made_meanwhile(scene: RetrievalIndex) -> None:
    """The index is trained off the request path: requests search exactly until it is in, and
    the adds and deletes made while it trained are applied before it is used."""
    source = _Source(scene.descriptors[:3000])
    builder = BackgroundTrainer("retrieval index")
    gate = threading.Event()
    builder.schedule("gate", gate.wait)  # the build queues behind this job
    # every list visited: a row mapped wrongly after the catch-up is the only way to miss
    cache = RetrievalIndexCache(AnnOptions(min_references=2000, nprobe=64), builder=builder)
    try:
        index = cache.index(source)
        assert index.ann is None and len(index.image_ids) == 3000  # exact meanwhile
        for i in range(0, 100):
            del source.vectors[f"r{i}"]
        source.vectors.update({f"r{i}": scene.descriptors[i] for i in range(3000, 3200)})
        source.rev = 2
        index = cache.index(source)
        assert index.ann is None and len(index.image_ids) == 3100
        gate.set()
        builder.wait(60)
    finally:
        gate.set()
        builder.shutdown()
    index = cache.index(source)  # same revision: the cached index, now with faiss
    assert index.ann is not None and index.ann.index.ntotal == 3100
    for row in (0, 50, 99):  # deleted meanwhile: gone from faiss
        rows, _ = search_index(index, scene.descriptors[row], 10)
        assert f"r{row}" not in {index.image_ids[r] for r in rows}
    for i in (3000, 3100, 3199):  # added meanwhile: found by its own vector
        rows, _ = search_index(index, scene.descriptors[i], 1)
        assert index.image_ids[rows[0]] == f"r{i}"
    rng = np.random.default_rng(3)
    assert recall_at_10(index, queries_of(rng, 30), None) >= 0.99
