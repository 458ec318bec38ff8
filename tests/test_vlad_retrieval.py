"""VLAD retrieval over a map's own vocabulary: trained automatically once the map is big
enough, versioned, kept up to date through adds and deletes without retraining, re-trained on
demand (API and CLI path) from stored descriptors only; on a real SQLite file and PostgreSQL."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import numpy as np
import pytest
from sqlalchemy import select

from app.schemas.images import ImageMetadata
from app.usecases import reindex
from app.usecases.images import add_reference_image
from app.usecases.localize import reference_store
from db import vocabulary
from db.migrate import upgrade
from db.models import FeatureArray, MapVocabulary, ReferenceImage
from db.repositories.images import ImageRepository
from db.repositories.maps import MapRepository
from db.session import make_engine, make_session_factory
from db.store import SqlReferenceStore
from db.vocabulary import STAGED_PREFIX, SqlVocabularyStore
from services.components import Localizers
from services.geometry.rigid import rotation_error_deg
from services.localization.localizer import Localizer
from services.retrieval import vlad_index
from services.retrieval.cache import RetrievalIndexCache
from services.retrieval.policy import MIN_IMAGES, NUM_CENTERS
from services.retrieval.search import top_k
from services.retrieval.training import BackgroundTrainer
from services.retrieval.vlad import encode, train_vocabulary
from services.retrieval.vlad_index import VladIndexer
from tests.conftest import create_map, image_metadata, make_client, upload_view
from tools.synthetic.scene import SyntheticView, encode_png


def test_vocabulary_lifecycle(
    database_url: str,
    localizer: Localizer,
    localizers: Localizers,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    engine = make_engine(database_url)
    upgrade(engine)
    sessions = make_session_factory(engine)
    with sessions.begin() as session:
        map_id = MapRepository(session).create("vlad", None).id

    def add(view: SyntheticView) -> str:
        image = ImageMetadata.model_validate(image_metadata(view)).to_new_image()
        return add_reference_image(sessions, localizers, map_id, image, encode_png(view.image)).id

    def store(cache: RetrievalIndexCache | None = None) -> SqlReferenceStore:
        return reference_store(sessions, map_id, localizer, cache)

    ids = [add(v) for v in reference_views[: MIN_IMAGES - 1]]
    small = store().retrieval_index()
    assert small.vocabulary is None and len(small.image_ids) == MIN_IMAGES - 1  # thumbnails

    ids += [add(v) for v in reference_views[MIN_IMAGES - 1 :]]
    cache = RetrievalIndexCache()
    index = store(cache).retrieval_index()  # the map is big enough: trained and encoded
    assert index.vocabulary is not None and index.vocabulary_version == 1
    assert sorted(index.image_ids) == sorted(ids)
    assert index.descriptors.shape == (len(ids), NUM_CENTERS * 128)
    with sessions() as session:
        versions = session.scalars(
            select(ReferenceImage.vlad_version).where(ReferenceImage.map_id == map_id)
        ).all()
        assert set(versions) == {1}

    # the query's top-5 by VLAD holds one of its three nearest references in pose
    # (distance in scene units + rotation / 30°); the thumbnail manages 8 of 10 here
    poses = {
        image_id: view.cam_from_world for image_id, view in zip(ids, reference_views, strict=True)
    }
    hits = 0
    for view in query_views:
        query = encode(localizer.extractor.extract(view.image).descriptors, index.vocabulary)
        rows, _ = top_k(query, index.descriptors, 5)
        pose = view.cam_from_world
        gap = {
            i: float(np.linalg.norm(p.center - pose.center))
            + rotation_error_deg(p.rotation, pose.rotation) / 30.0
            for i, p in poses.items()
        }
        nearest = sorted(gap, key=gap.__getitem__)[:3]
        hits += any(index.image_ids[r] in nearest for r in rows)
    assert hits >= 9, hits

    # deletes and adds follow without retraining
    with sessions.begin() as session:
        assert ImageRepository(session).delete(map_id, ids[0])
    ids = ids[1:]
    ids.append(add(query_views[0]))
    index = store(cache).retrieval_index()
    assert index.vocabulary_version == 1 and sorted(index.image_ids) == sorted(ids)
    fresh = store().retrieval_index()
    order = [fresh.image_ids.index(i) for i in index.image_ids]
    np.testing.assert_array_equal(index.descriptors, fresh.descriptors[order])

    # forced re-training: a new version, every reference re-encoded, the cache reloads
    report = VladIndexer(SqlVocabularyStore(sessions, map_id, localizer.extractor.name)).train()
    assert (report.version, report.encoded_images, report.trained_images) == (2, len(ids), len(ids))
    index = store(cache).retrieval_index()
    assert index.vocabulary_version == 2 and sorted(index.image_ids) == sorted(ids)
    with sessions() as session:
        assert session.get(MapVocabulary, (map_id, localizer.extractor.name)).version == 2
        vlad_rows = session.scalars(
            select(FeatureArray.image_id).where(FeatureArray.kind == "vlad")
        ).all()
        assert sorted(vlad_rows) == sorted(ids)  # the deleted reference's vector went with it
        staged = session.scalars(
            select(FeatureArray.kind).where(FeatureArray.kind.startswith(STAGED_PREFIX))
        ).all()
        assert staged == []  # the staged vectors became the current ones

    with sessions.begin() as session:
        MapRepository(session).delete(map_id)
    with sessions() as session:
        assert session.scalars(select(MapVocabulary)).all() == []
    engine.dispose()


def test_reindex_endpoint(
    database_url: str, localizer: Localizer, reference_views: list[SyntheticView]
) -> None:
    keys = "adm:admin,cli:client"
    with make_client(database_url, localizer, api_keys=keys) as client:
        admin = {"X-API-Key": "adm"}
        missing = client.post("/v1/maps/nope/reindex", headers=admin)
        assert missing.status_code == 404
        assert missing.headers["content-type"] == "application/problem+json"
        assert missing.json()["type"] == "https://slloc.dev/problems/not-found"

        client.headers.update(admin)
        map_id = create_map(client, "reindexed")
        empty = client.post(f"/v1/maps/{map_id}/reindex")
        assert empty.status_code == 409, empty.text
        assert "too few" in empty.json()["detail"]

        for view in reference_views[:3]:
            assert upload_view(client, map_id, view).status_code == 201  # type: ignore[attr-defined]
        forbidden = client.post(f"/v1/maps/{map_id}/reindex", headers={"X-API-Key": "cli"})
        assert forbidden.status_code == 403

        body = client.post(f"/v1/maps/{map_id}/reindex").json()
        assert body["vocabulary_version"] == 1 and body["encoded_images"] == 3
        assert body["num_centers"] == NUM_CENTERS and body["trained_images"] == 3
        again = client.post(f"/v1/maps/{map_id}/reindex").json()
        assert again["vocabulary_version"] == 2


def test_reindex_waits_for_a_training_running_elsewhere(
    database_url: str,
    localizer: Localizer,
    reference_views: list[SyntheticView],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """An explicit reindex trains holding the map's training lock, once the trainer that
    holds it (a background training, another replica; here the test) is done, so that two
    trainings of one map never run at once."""
    waiting = threading.Event()
    held_while_training: list[bool] = []
    real_exclusive, real_train = vocabulary.exclusive, VladIndexer.train

    @contextmanager
    def announcing(engine: object, name: str, wait_s: float = 0.0) -> Iterator[bool]:
        if wait_s:
            waiting.set()
        with real_exclusive(engine, name, wait_s) as held:  # type: ignore[arg-type]
            yield held

    def probing(self: VladIndexer, yield_to_newer: bool = False) -> object:
        with real_exclusive(engine, lock_name) as free:
            held_while_training.append(not free)
        return real_train(self, yield_to_newer)

    monkeypatch.setattr(vocabulary, "exclusive", announcing)
    monkeypatch.setattr(VladIndexer, "train", probing)
    engine = make_engine(database_url)
    with make_client(database_url, localizer) as client, ThreadPoolExecutor(1) as pool:
        map_id = create_map(client, "waiting")
        for view in reference_views[:3]:
            assert upload_view(client, map_id, view).status_code == 201  # type: ignore[attr-defined]
        lock_name = f"vocabulary:{map_id}:{localizer.extractor.name}"
        with real_exclusive(engine, lock_name) as held:
            assert held
            reindexed = pool.submit(client.post, f"/v1/maps/{map_id}/reindex")
            assert waiting.wait(60)
            assert not reindexed.done() and held_while_training == []
        response = reindexed.result(timeout=120)
    engine.dispose()
    assert response.status_code == 200, response.text
    assert response.json()["vocabulary_version"] == 1
    assert held_while_training == [True]


def test_reindex_answers_409_when_a_training_elsewhere_outlasts_its_wait(
    database_url: str,
    localizer: Localizer,
    reference_views: list[SyntheticView],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The reindex waits for a training running elsewhere at most TRAINING_WAIT_S, then
    answers 409 and trains nothing; once that training is done it trains."""
    monkeypatch.setattr(reindex, "TRAINING_WAIT_S", 0.5)
    engine = make_engine(database_url)
    with make_client(database_url, localizer) as client:
        map_id = create_map(client, "busy")
        for view in reference_views[:3]:
            assert upload_view(client, map_id, view).status_code == 201  # type: ignore[attr-defined]
        lock_name = f"vocabulary:{map_id}:{localizer.extractor.name}"
        with vocabulary.exclusive(engine, lock_name) as held:
            assert held
            start = time.monotonic()
            refused = client.post(f"/v1/maps/{map_id}/reindex")
            waited = time.monotonic() - start
        assert refused.status_code == 409, refused.text
        assert refused.headers["content-type"] == "application/problem+json"
        assert "being trained elsewhere" in refused.json()["detail"]
        assert 0.5 <= waited < 30
        trained = client.post(f"/v1/maps/{map_id}/reindex")
    engine.dispose()
    assert trained.status_code == 200, trained.text
    assert trained.json()["vocabulary_version"] == 1


def test_global_model_maps_have_no_vocabulary(database_url: str, localizer: Localizer) -> None:
    """With an ONNX global-descriptor model configured, retrieval never uses VLAD."""
    with make_client(database_url, localizer, global_model="/models/global.onnx") as client:
        map_id = create_map(client, "learned")
        response = client.post(f"/v1/maps/{map_id}/reindex")
        assert response.status_code == 409
        assert "SLLOC_GLOBAL_MODEL" in response.json()["detail"]


def test_training_runs_off_the_request_path(
    database_url: str,
    localizer: Localizer,
    localizers: Localizers,
    reference_views: list[SyntheticView],
) -> None:
    """Adds that make a vocabulary due hand it to the trainer; until it is published, reads go
    on at once with the previous index (here: global descriptors)."""
    engine = make_engine(database_url)
    upgrade(engine)
    sessions = make_session_factory(engine)
    with sessions.begin() as session:
        map_id = MapRepository(session).create("background", None).id
    trainer = BackgroundTrainer()
    gate = threading.Event()
    trainer.schedule("held", lambda: gate.wait(60))  # keeps the single worker busy
    ids = [
        add_reference_image(
            sessions,
            localizers,
            map_id,
            ImageMetadata.model_validate(image_metadata(view)).to_new_image(),
            encode_png(view.image),
            trainer=trainer,
        ).id
        for view in reference_views[:MIN_IMAGES]
    ]
    cache = RetrievalIndexCache()
    store = reference_store(sessions, map_id, localizer, cache, trainer=trainer)
    before = store.retrieval_index()
    assert before.vocabulary is None and sorted(before.image_ids) == sorted(ids)
    assert trainer.pending() == 2  # the held job and one training, however many asked for it
    gate.set()
    trainer.wait(120)
    after = store.retrieval_index()
    assert after.vocabulary_version == 1 and sorted(after.image_ids) == sorted(ids)
    assert after.descriptors.shape == (len(ids), NUM_CENTERS * 128)
    trainer.shutdown()
    engine.dispose()


def test_add_endpoint_trains_in_the_background(
    database_url: str, localizer: Localizer, reference_views: list[SyntheticView]
) -> None:
    with make_client(database_url, localizer) as client:
        map_id = create_map(client, "crossing")
        for view in reference_views[:MIN_IMAGES]:
            assert upload_view(client, map_id, view).status_code == 201  # type: ignore[attr-defined]
        client.app.state.vocabulary_trainer.wait(120)  # type: ignore[attr-defined]
        engine = make_engine(database_url)
        with make_session_factory(engine)() as session:
            vocabulary = session.get(MapVocabulary, (map_id, localizer.extractor.name))
            assert vocabulary is not None and vocabulary.version == 1
            assert vocabulary.trained_images == MIN_IMAGES
        engine.dispose()


def test_background_training_yields_to_an_explicit_one(
    database_url: str,
    localizer: Localizer,
    localizers: Localizers,
    reference_views: list[SyntheticView],
) -> None:
    """A due training that finds a version published meanwhile keeps that one; an explicit
    training publishes on top of it."""
    engine = make_engine(database_url)
    upgrade(engine)
    sessions = make_session_factory(engine)
    with sessions.begin() as session:
        map_id = MapRepository(session).create("racing", None).id
    for view in reference_views[:3]:
        image = ImageMetadata.model_validate(image_metadata(view)).to_new_image()
        add_reference_image(sessions, localizers, map_id, image, encode_png(view.image))
    store = SqlVocabularyStore(sessions, map_id, localizer.extractor.name)
    explicit = VladIndexer(store).train()
    assert explicit.version == 1
    state = store.published()
    assert state is not None
    ids = store.reference_ids()
    vectors = {i: np.ones(state.vocabulary.dimension, np.float32) for i in ids}

    def encoder(d: np.ndarray) -> np.ndarray:
        return np.ones(state.vocabulary.dimension, np.float32)

    store.stage(vectors, "late0000")
    kept = store.publish(state.vocabulary, "late0000", 3, None, encoder, yield_to_newer=True)
    assert kept.version == 1  # the version published meanwhile stays
    store.stage(vectors, "late0001")
    on_top = store.publish(state.vocabulary, "late0001", 3, None, encoder, yield_to_newer=False)
    assert on_top.version == 2
    with sessions() as session:
        kinds = set(session.scalars(select(FeatureArray.kind)).all())
        assert not any(k.startswith(STAGED_PREFIX) for k in kinds)
    engine.dispose()


def test_training_reads_a_few_references_at_a_time(
    database_url: str,
    localizer: Localizer,
    localizers: Localizers,
    reference_views: list[SyntheticView],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A vocabulary's training and encoding read the stored descriptors a few references at
    a time (what the memory bound's ``vocabulary`` term counts), and train the vocabulary
    that all the descriptors read at once would."""
    read, sample = 4, 1000
    monkeypatch.setattr(vlad_index, "VOCABULARY_READ", read)
    monkeypatch.setattr(vlad_index, "VOCABULARY_SAMPLE", sample)
    engine = make_engine(database_url)
    upgrade(engine)
    sessions = make_session_factory(engine)
    with sessions.begin() as session:
        map_id = MapRepository(session).create("batches", None).id
    ids = []
    for view in reference_views:
        image = ImageMetadata.model_validate(image_metadata(view)).to_new_image()
        ids.append(
            add_reference_image(sessions, localizers, map_id, image, encode_png(view.image)).id
        )
    reads: list[int] = []

    class Recording(SqlVocabularyStore):
        def descriptors(self, image_ids: list[str]) -> dict[str, np.ndarray]:
            reads.append(len(image_ids))
            return super().descriptors(image_ids)

    store = Recording(sessions, map_id, localizer.extractor.name)
    report = VladIndexer(store).train()
    trained = store.published()
    everything = SqlVocabularyStore(sessions, map_id, localizer.extractor.name).descriptors(ids)
    engine.dispose()
    assert report.trained_images == report.encoded_images == len(ids)
    # counted, sampled, encoded: three passes over the references, a few at a time
    assert max(reads) == read and sum(reads) == 3 * len(ids)
    assert sum(d.shape[0] for d in everything.values()) > sample  # the sample is drawn
    at_once = train_vocabulary(
        [everything[i] for i in ids], num_centers=report.num_centers, max_points=sample
    )
    assert trained is not None
    np.testing.assert_array_equal(trained.vocabulary.centers, at_once.centers)
