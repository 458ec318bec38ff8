"""A map deleted while its retrieval vocabulary is being trained, at every step of the
training (deterministically: the step deletes the map, then runs): the explicit reindex
answers 404, a localize that trains inline answers normally, a localize whose training runs
in the background answers normally and the job's failure is logged, never raised; nothing of
the map is left behind. On a real SQLite file and PostgreSQL."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Any

import pytest
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from app.schemas.images import ImageMetadata
from app.usecases.errors import NotFoundError
from app.usecases.images import add_reference_image
from app.usecases.localize import LocalizeContext, LocalizeRequest, localize
from db.migrate import upgrade
from db.models import FeatureArray, Map, MapVocabulary, ReferenceImage
from db.repositories.maps import MapRepository
from db.session import make_engine, make_session_factory
from db.vocabulary import SqlVocabularyStore
from services.components import Localizers
from services.estimators.base import FailureReason
from services.localization.localizer import Localizer
from services.retrieval import vlad_index
from services.retrieval.contracts import VocabularyError
from services.retrieval.training import BackgroundTrainer
from services.retrieval.vlad_index import VladIndexer
from tests.conftest import create_map, image_metadata, make_client, upload_view
from tools.synthetic.scene import SyntheticView, encode_png

TRAINING_STEPS = ["reference_ids", "descriptors", "stage", "publish"]


def delete_map_before(monkeypatch: pytest.MonkeyPatch, step: str) -> None:
    """The first call of ``SqlVocabularyStore.<step>`` deletes the store's map, then runs."""
    real = getattr(SqlVocabularyStore, step)
    deleted = False

    def deleting(self: SqlVocabularyStore, *args: Any, **kwargs: Any) -> Any:
        nonlocal deleted
        if not deleted:
            deleted = True
            with self.sessions.begin() as session:
                MapRepository(session).delete(self.map_id)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(SqlVocabularyStore, step, deleting)


def force_training_due(monkeypatch: pytest.MonkeyPatch) -> None:
    """A map without a vocabulary is due at any size (three references train one here)."""
    monkeypatch.setattr(vlad_index, "training_due", lambda count, trained: trained is None)


def assert_nothing_left(sessions: sessionmaker[Session]) -> None:
    with sessions() as session:
        for table in (Map, ReferenceImage, FeatureArray, MapVocabulary):
            assert session.scalar(select(func.count()).select_from(table)) == 0, table


@pytest.fixture
def sessions(database_url: str) -> Iterator[sessionmaker[Session]]:
    engine = make_engine(database_url)
    upgrade(engine)
    yield make_session_factory(engine)
    engine.dispose()


def small_map(
    sessions: sessionmaker[Session], localizers: Localizers, views: list[SyntheticView]
) -> str:
    with sessions.begin() as session:
        map_id = MapRepository(session).create("racing", None).id
    for view in views:
        image = ImageMetadata.model_validate(image_metadata(view)).to_new_image()
        add_reference_image(sessions, localizers, map_id, image, encode_png(view.image))
    return map_id


@pytest.mark.parametrize("step", TRAINING_STEPS)
def test_reindex_of_a_map_deleted_while_training_is_404(
    step: str,
    database_url: str,
    localizer: Localizer,
    reference_views: list[SyntheticView],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    with make_client(database_url, localizer) as client:
        map_id = create_map(client, "reindexed")
        for view in reference_views[:3]:
            assert upload_view(client, map_id, view).status_code == 201  # type: ignore[attr-defined]
        delete_map_before(monkeypatch, step)
        response = client.post(f"/v1/maps/{map_id}/reindex")
        assert response.status_code == 404, response.text
        assert response.headers["content-type"] == "application/problem+json"
        assert response.json()["type"] == "https://slloc.dev/problems/not-found"


@pytest.mark.parametrize("step", ["count", "published", *TRAINING_STEPS])
def test_localize_training_inline_survives_the_delete(
    step: str,
    sessions: sessionmaker[Session],
    localizers: Localizers,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Without a trainer (the offline tools), a due vocabulary is trained before the search."""
    map_id = small_map(sessions, localizers, reference_views[:3])
    force_training_due(monkeypatch)
    delete_map_before(monkeypatch, step)
    try:
        result = localize(
            LocalizeContext(sessions, localizers, max_top_k=10),
            map_id,
            LocalizeRequest(),
            encode_png(query_views[0].image),
        )
    except NotFoundError:
        pass  # the map went before the localize read it: as good an answer
    else:
        assert not result.localized
        assert result.reason == FailureReason.NO_REFERENCES.value
    assert_nothing_left(sessions)


@pytest.mark.parametrize("step", ["stale_ids", "descriptors", "replace_vectors"])
def test_localize_encoding_new_references_survives_the_delete(
    step: str,
    sessions: sessionmaker[Session],
    localizers: Localizers,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A published vocabulary encodes the references added since before the search."""
    map_id = small_map(sessions, localizers, reference_views[:3])
    VladIndexer(SqlVocabularyStore(sessions, map_id, localizers.served.extractor.name)).train()
    image = ImageMetadata.model_validate(image_metadata(reference_views[3])).to_new_image()
    add_reference_image(
        sessions, localizers, map_id, image, encode_png(reference_views[3].image)
    )  # not encoded yet
    delete_map_before(monkeypatch, step)
    result = localize(
        LocalizeContext(sessions, localizers, max_top_k=10),
        map_id,
        LocalizeRequest(),
        encode_png(query_views[0].image),
    )
    assert not result.localized and result.reason == FailureReason.NO_REFERENCES.value
    assert_nothing_left(sessions)


@pytest.mark.parametrize("step", ["count", "published", *TRAINING_STEPS])
def test_localize_training_in_the_background_survives_the_delete(
    step: str,
    database_url: str,
    localizer: Localizer,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    with make_client(database_url, localizer) as client:
        map_id = create_map(client, "background")
        for view in reference_views[:3]:
            assert upload_view(client, map_id, view).status_code == 201  # type: ignore[attr-defined]
        force_training_due(monkeypatch)
        delete_map_before(monkeypatch, step)
        response = client.post(
            f"/v1/maps/{map_id}/localize",
            files={"image": ("q.png", encode_png(query_views[0].image), "image/png")},
        )
        assert response.status_code in (200, 404), response.text
        if response.status_code == 200:  # the training steps run after it answered
            body = response.json()
            assert body["localized"] or body["reason"] in set(FailureReason)
        client.app.state.vocabulary_trainer.wait(60)  # type: ignore[attr-defined]
        assert client.get(f"/v1/maps/{map_id}").status_code == 404
    failures = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert all(r.exc_info and r.exc_info[0] is VocabularyError for r in failures), failures


def test_background_job_of_a_deleted_map_is_logged(
    sessions: sessionmaker[Session],
    localizers: Localizers,
    reference_views: list[SyntheticView],
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    map_id = small_map(sessions, localizers, reference_views[:3])
    delete_map_before(monkeypatch, "publish")
    indexer = VladIndexer(SqlVocabularyStore(sessions, map_id, localizers.served.extractor.name))
    with pytest.raises(VocabularyError, match="deleted"):
        indexer.train()
    map_id = small_map(sessions, localizers, reference_views[:3])
    delete_map_before(monkeypatch, "stage")
    trainer = BackgroundTrainer()
    indexer = VladIndexer(SqlVocabularyStore(sessions, map_id, localizers.served.extractor.name))
    assert trainer.schedule(map_id, indexer.train)
    trainer.wait(60)  # the job's error stays in the worker
    trainer.shutdown()
    (failure,) = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert failure.exc_info is not None and failure.exc_info[0] is VocabularyError
    assert_nothing_left(sessions)
