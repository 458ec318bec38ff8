"""Several threads add, delete and localize on one map at once."""

from __future__ import annotations

import random
import threading
from collections import Counter

from fastapi.testclient import TestClient
from sqlalchemy import create_engine
from sqlalchemy.orm import Session

from db.repositories.images import ImageRepository
from tests.conftest import create_map, upload_view
from tools.synthetic.scene import SyntheticView, encode_png


def test_concurrent_add_delete_localize(
    client: TestClient,
    database_url: str,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    map_id = create_map(client)
    seeded = [upload_view(client, map_id, v).json()["id"] for v in reference_views[:6]]
    statuses: Counter[tuple[str, int]] = Counter()
    lock = threading.Lock()
    errors: list[BaseException] = []

    def record(kind: str, status: int) -> None:
        with lock:
            statuses[(kind, status)] += 1

    def adder(views: list[SyntheticView]) -> None:
        for view in views:
            record("add", upload_view(client, map_id, view).status_code)

    def deleter(ids: list[str]) -> None:
        for image_id in ids * 2:  # the second round deletes what is gone: 404
            record("delete", client.delete(f"/v1/maps/{map_id}/images/{image_id}").status_code)

    def localizer(views: list[SyntheticView]) -> None:
        for view in views:
            response = client.post(
                f"/v1/maps/{map_id}/localize",
                files={"image": ("q.png", encode_png(view.image), "image/png")},
            )
            record("localize", response.status_code)

    def guarded(fn, *args):  # type: ignore[no-untyped-def]
        def run() -> None:
            try:
                fn(*args)
            except BaseException as exc:
                errors.append(exc)

        return threading.Thread(target=run)

    random.Random(0).shuffle(seeded)
    threads = [
        guarded(adder, reference_views[6:11]),
        guarded(adder, reference_views[11:16]),
        guarded(deleter, seeded[:4]),
        guarded(localizer, query_views[:3]),
        guarded(localizer, query_views[3:6]),
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=600)
    assert not errors, errors
    unexpected = {
        k: n
        for k, n in statuses.items()
        if k not in {("add", 201), ("delete", 204), ("delete", 404), ("localize", 200)}
    }
    assert not unexpected, unexpected
    assert statuses[("add", 201)] == 10
    assert statuses[("delete", 204)] == 4 and statuses[("delete", 404)] == 4
    assert statuses[("localize", 200)] == 6

    engine = create_engine(database_url)
    with Session(engine) as session:
        repo = ImageRepository(session)
        assert repo.count_orphan_arrays() == 0
        assert repo.page(map_id, 0, 100)[1] == 6 + 10 - 4
    engine.dispose()
