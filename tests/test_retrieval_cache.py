"""The in-memory retrieval index follows adds and deletes made anywhere (other processes
included), reading only what changed."""

from __future__ import annotations

import numpy as np

from app.schemas.images import ImageMetadata
from app.usecases.images import add_reference_image
from app.usecases.localize import reference_store
from db.migrate import upgrade
from db.models import Map
from db.repositories.images import ImageRepository
from db.repositories.maps import MapRepository
from db.session import make_engine, make_session_factory
from db.store import SqlReferenceStore
from services.components import Localizers
from services.retrieval.cache import RetrievalIndexCache
from tests.conftest import image_metadata
from tools.synthetic.scene import SyntheticView, encode_png


def test_cache_follows_adds_and_deletes(
    database_url: str, localizers: Localizers, reference_views: list[SyntheticView]
) -> None:
    engine = make_engine(database_url)
    upgrade(engine)
    sessions = make_session_factory(engine)
    with sessions.begin() as session:
        map_id = MapRepository(session).create("cached", None).id

    def add(view: SyntheticView) -> str:
        image = ImageMetadata.model_validate(image_metadata(view)).to_new_image()
        return add_reference_image(sessions, localizers, map_id, image, encode_png(view.image)).id

    def store(cache: RetrievalIndexCache) -> SqlReferenceStore:
        return reference_store(sessions, map_id, localizers.served, cache)

    ids = [add(v) for v in reference_views[:3]]
    cache = RetrievalIndexCache()
    first = store(cache).retrieval_index()
    assert sorted(first.image_ids) == sorted(ids)
    assert store(cache).retrieval_index() is first  # unchanged map: served from memory

    other_process = RetrievalIndexCache()
    assert sorted(store(other_process).retrieval_index().image_ids) == sorted(ids)
    ids.append(add(reference_views[3]))  # this "process" writes; the other must notice
    with sessions.begin() as session:
        assert ImageRepository(session).delete(map_id, ids[0])
    for c in (cache, other_process):
        index = store(c).retrieval_index()
        assert sorted(index.image_ids) == sorted(ids[1:])
        fresh = store(None).retrieval_index()  # uncached: straight from the database
        order = [fresh.image_ids.index(i) for i in index.image_ids]
        np.testing.assert_array_equal(index.descriptors, fresh.descriptors[order])
        np.testing.assert_array_equal(index.centers, fresh.centers[order])

    with sessions.begin() as session:
        assert session.get(Map, map_id).revision == 5  # 4 adds, 1 delete
        MapRepository(session).delete(map_id)
    assert store(cache).retrieval_index().image_ids == []
    engine.dispose()
