"""Writers of one map take its rows in one order (the map row, then its images, then their
arrays), so they wait for each other instead of deadlocking (PostgreSQL answers a deadlock
by failing one transaction: a 500). Each test holds a lock the way one writer does, starts
the other writer in a thread, then goes on; both must finish. On a real SQLite file and
PostgreSQL (SQLite serializes writers: it must pass there too)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from sqlalchemy import select, update
from sqlalchemy.orm import Session, sessionmaker

from app.schemas.images import ImageMetadata
from app.usecases.images import add_reference_image, delete_image
from db import vocabulary
from db.migrate import upgrade
from db.models import FeatureArray, Map, ReferenceImage
from db.repositories.maps import MapRepository
from db.session import make_engine, make_session_factory
from db.vocabulary import SqlVocabularyStore
from services.localization.localizer import Localizer
from tests.conftest import image_metadata
from tools.synthetic.scene import SyntheticView, encode_png

# long enough for the other writer to reach its first lock
SETTLE_S = 0.5


@pytest.fixture
def sessions(database_url: str) -> Iterator[sessionmaker[Session]]:
    engine = make_engine(database_url)
    upgrade(engine)
    yield make_session_factory(engine)
    engine.dispose()


@pytest.fixture
def two_images(
    sessions: sessionmaker[Session], localizer: Localizer, reference_views: list[SyntheticView]
) -> tuple[str, list[str]]:
    with sessions.begin() as session:
        map_id = MapRepository(session).create("locked", None).id
    ids = []
    for view in reference_views[:2]:
        image = ImageMetadata.model_validate(image_metadata(view)).to_new_image()
        ids.append(
            add_reference_image(sessions, localizer, map_id, image, encode_png(view.image)).id
        )
    return map_id, ids


def _in_thread(work: Callable[[], None]) -> tuple[threading.Thread, list[BaseException]]:
    errors: list[BaseException] = []

    def run() -> None:
        try:
            work()
        except BaseException as exc:
            errors.append(exc)

    thread = threading.Thread(target=run)
    thread.start()
    return thread, errors


def test_image_deleted_while_a_vocabulary_publishes(
    sessions: sessionmaker[Session], two_images: tuple[str, list[str]]
) -> None:
    """The publisher locks the map, then updates the map's images; a delete meanwhile."""
    map_id, (doomed, kept) = two_images
    with sessions.begin() as publisher:
        publisher.get(Map, map_id, with_for_update=True)
        thread, errors = _in_thread(lambda: delete_image(sessions, map_id, doomed))
        time.sleep(SETTLE_S)
        publisher.execute(
            update(ReferenceImage).where(ReferenceImage.map_id == map_id).values(vlad_version=1)
        )
    thread.join(30)
    assert not thread.is_alive() and not errors, errors
    with sessions() as session:
        assert list(session.scalars(select(ReferenceImage.id))) == [kept]


def test_image_deleted_while_its_vectors_are_replaced(
    sessions: sessionmaker[Session],
    two_images: tuple[str, list[str]],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Replacing vectors drops the images' old vectors, then writes the new ones; a delete
    of one of the images in between. Both finish, the image is gone with its arrays."""
    map_id, (doomed, kept) = two_images
    vectors = {image_id: np.ones(4, np.float32) for image_id in (doomed, kept)}
    with sessions.begin() as session:  # the vectors being replaced
        vocabulary._write(session, vectors, vocabulary.VLAD_KIND)
    real_write = vocabulary._write
    deleter: list[tuple[threading.Thread, list[BaseException]]] = []

    def write_after_a_delete_started(session: Session, *args: Any) -> None:
        deleter.append(_in_thread(lambda: delete_image(sessions, map_id, doomed)))
        time.sleep(SETTLE_S)
        real_write(session, *args)

    monkeypatch.setattr(vocabulary, "_write", write_after_a_delete_started)
    store = SqlVocabularyStore(sessions, map_id, "unused")
    replaced = store.replace_vectors(vectors, 1)
    thread, errors = deleter[0]
    thread.join(30)
    assert not thread.is_alive() and not errors, errors
    assert replaced  # the replacement went first, the delete waited for it
    with sessions() as session:
        assert list(session.scalars(select(ReferenceImage.id))) == [kept]
        orphans = select(FeatureArray).where(FeatureArray.image_id == doomed)
        assert session.scalars(orphans).first() is None
