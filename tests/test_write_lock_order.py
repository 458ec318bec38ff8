"""Writers of one map take its rows in one order (the map row, then its images, then their
arrays), so they wait for each other instead of deadlocking (PostgreSQL answers a deadlock
by failing one transaction: a 500). Each test holds a lock the way one writer does, starts
the other writer in a thread, waits until that writer has reached a lock it waits on (or has
finished), then goes on; both must finish. On a real SQLite file and PostgreSQL (SQLite
serializes writers: it must pass there too)."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from sqlalchemy import Engine, event, select, text, update
from sqlalchemy.orm import Session, sessionmaker

from app.schemas.images import ImageMetadata
from app.usecases.images import add_reference_image, delete_image
from db import vocabulary
from db.migrate import upgrade
from db.models import FeatureArray, Map, ReferenceImage
from db.repositories.maps import MapRepository
from db.session import make_engine, make_session_factory
from db.vocabulary import SqlVocabularyStore
from services.components import Localizers
from tests.conftest import image_metadata
from tests.polling import wait_until
from tools.synthetic.scene import SyntheticView, encode_png

WRITES = ("INSERT", "UPDATE", "DELETE")


@pytest.fixture
def engine(database_url: str) -> Iterator[Engine]:
    engine = make_engine(database_url)
    upgrade(engine)
    yield engine
    engine.dispose()


@pytest.fixture
def sessions(engine: Engine) -> sessionmaker[Session]:
    return make_session_factory(engine)


class OtherWriter:
    """``work`` in a thread, and whether it has reached a lock it waits on.

    PostgreSQL shows it: the writer's backend waits on a lock (``pg_stat_activity``). SQLite
    has one lock, the database's write lock, and no view of who waits for it: the writer has
    reached it once it is inside a write statement (SQLAlchemy's cursor events), which waits
    while the test's transaction writes."""

    def __init__(self, engine: Engine, work: Callable[[], None]) -> None:
        self.engine = engine
        self.errors: list[BaseException] = []
        self._statements: dict[int, str] = {}  # thread id → statement started, not ended
        event.listen(engine, "before_cursor_execute", self._started)
        event.listen(engine, "after_cursor_execute", self._ended)
        event.listen(engine, "handle_error", self._failed)
        self.thread = threading.Thread(target=self._run, args=(work,))
        self.thread.start()

    def _run(self, work: Callable[[], None]) -> None:
        try:
            work()
        except BaseException as exc:
            self.errors.append(exc)

    def _started(self, _conn: Any, _cursor: Any, statement: str, *_: Any) -> None:
        self._statements[threading.get_ident()] = statement

    def _ended(self, *_: Any) -> None:
        self._statements.pop(threading.get_ident(), None)

    def _failed(self, _context: Any) -> None:
        self._statements.pop(threading.get_ident(), None)

    def waits_on_a_lock(self) -> bool:
        if self.engine.dialect.name == "postgresql":
            with self.engine.connect() as conn:
                return bool(
                    conn.scalar(
                        text(
                            "SELECT count(*) FROM pg_stat_activity WHERE wait_event_type = "
                            "'Lock' AND datname = current_database()"
                        )
                    )
                )
        statement = self._statements.get(self.thread.ident or 0, "")
        return statement.lstrip().upper().startswith(WRITES)

    def reached_a_lock(self, timeout_s: float = 30.0) -> bool:
        """Wait until the writer waits on a lock or has finished."""
        return wait_until(lambda: not self.thread.is_alive() or self.waits_on_a_lock(), timeout_s)

    def finish(self, timeout_s: float = 30.0) -> None:
        self.thread.join(timeout_s)
        event.remove(self.engine, "before_cursor_execute", self._started)
        event.remove(self.engine, "after_cursor_execute", self._ended)
        event.remove(self.engine, "handle_error", self._failed)
        assert not self.thread.is_alive(), "the other writer did not finish"
        assert not self.errors, self.errors


@pytest.fixture
def two_images(
    sessions: sessionmaker[Session], localizers: Localizers, reference_views: list[SyntheticView]
) -> tuple[str, list[str]]:
    with sessions.begin() as session:
        map_id = MapRepository(session).create("locked", None).id
    ids = []
    for view in reference_views[:2]:
        image = ImageMetadata.model_validate(image_metadata(view)).to_new_image()
        ids.append(
            add_reference_image(sessions, localizers, map_id, image, encode_png(view.image)).id
        )
    return map_id, ids


def test_image_deleted_while_a_vocabulary_publishes(
    engine: Engine, sessions: sessionmaker[Session], two_images: tuple[str, list[str]]
) -> None:
    """The publisher locks the map, then updates the map's images; a delete meanwhile."""
    map_id, (doomed, kept) = two_images
    with sessions.begin() as publisher:
        publisher.get(Map, map_id, with_for_update=True)
        deleter = OtherWriter(engine, lambda: delete_image(sessions, map_id, doomed))
        assert deleter.reached_a_lock()
        publisher.execute(
            update(ReferenceImage).where(ReferenceImage.map_id == map_id).values(vlad_version=1)
        )
    deleter.finish()
    with sessions() as session:
        assert list(session.scalars(select(ReferenceImage.id))) == [kept]


def test_image_deleted_while_its_vectors_are_replaced(
    engine: Engine,
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
    deleters: list[OtherWriter] = []

    def write_after_a_delete_started(session: Session, *args: Any) -> None:
        deleters.append(OtherWriter(engine, lambda: delete_image(sessions, map_id, doomed)))
        assert deleters[0].reached_a_lock()
        real_write(session, *args)

    monkeypatch.setattr(vocabulary, "_write", write_after_a_delete_started)
    store = SqlVocabularyStore(sessions, map_id, "unused")
    replaced = store.replace_vectors(vectors, 1)
    deleters[0].finish()
    assert replaced  # the replacement went first, the delete waited for it
    with sessions() as session:
        assert list(session.scalars(select(ReferenceImage.id))) == [kept]
        orphans = select(FeatureArray).where(FeatureArray.image_id == doomed)
        assert session.scalars(orphans).first() is None
