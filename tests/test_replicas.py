"""Two ``slloc serve`` processes on one PostgreSQL database stay consistent (issue #17): an add
on one is retrieved by the other's next localize, a delete acknowledged by one is never served
by the other, and vocabulary training runs once across both (a PostgreSQL advisory lock)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy import create_engine, select

from db.locks import exclusive
from db.models import MapVocabulary, ReferenceImage
from services.features.configs import SIFT
from services.retrieval.policy import MIN_IMAGES
from tests.conftest import create_map, fresh_postgres_database, upload_view
from tests.polling import wait_until
from tools.evaluation.server import LocalServer
from tools.synthetic.scene import SyntheticView, encode_png

pytestmark = pytest.mark.postgres

TRAINED = "VLAD vocabulary v"  # the line a process logs when it published a version it trained


@pytest.fixture(scope="module")
def database(postgres_admin_url: str) -> Iterator[str]:
    yield from fresh_postgres_database(postgres_admin_url)


@pytest.fixture(scope="module")
def replicas(database: str) -> Iterator[tuple[LocalServer, LocalServer]]:
    env = {
        "SLLOC_DATABASE_URL": database,
        "SLLOC_FEATURES": SIFT,
        "SLLOC_MODELS_DIR": "/nonexistent-models",
    }
    with LocalServer(env, log_level="info") as a, LocalServer(env, log_level="info") as b:
        yield a, b


def localize(url: str, map_id: str, view: SyntheticView) -> list[str]:
    """Ids of the references the server retrieved for ``view`` (top-k wide enough for all)."""
    response = httpx.post(
        f"{url}/v1/maps/{map_id}/localize",
        files={"image": (view.name, encode_png(view.image), "image/png")},
        data={"params": json.dumps({"top_k": 50})},
        timeout=120,
    )
    assert response.status_code == 200, response.text
    return [r["image_id"] for r in response.json()["retrieved"]]


def vocabulary_jobs(url: str) -> float:
    """Vocabulary trainings queued or running in the server at ``url`` (its ``/metrics``)."""
    response = httpx.get(f"{url}/metrics", timeout=30)
    assert response.status_code == 200, response.text
    for family in text_string_to_metric_families(response.text):
        for sample in family.samples:
            if sample.name == "slloc_background_jobs" and sample.labels["kind"] == "vocabulary":
                return sample.value
    raise AssertionError(f"{url}/metrics has no vocabulary jobs gauge")


def test_two_replicas_share_one_database(
    replicas: tuple[LocalServer, LocalServer],
    database: str,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    a, b = replicas
    engine = create_engine(database)
    with (
        httpx.Client(base_url=a.url, timeout=120) as on_a,
        httpx.Client(base_url=b.url, timeout=120) as on_b,
    ):
        map_id = create_map(on_a)  # type: ignore[arg-type]

        first = upload_view(on_b, map_id, reference_views[0])  # type: ignore[arg-type]
        assert first.status_code == 201  # type: ignore[attr-defined]
        ids = [first.json()["id"]]  # type: ignore[attr-defined]
        with engine.connect() as conn:  # the map's feature model names its lock
            feature_model = conn.scalar(
                select(ReferenceImage.feature_model).where(ReferenceImage.id == ids[0])
            )

        def trainers_idle() -> bool:
            """No training queued or running on either replica. An add or a localize
            schedules the training it finds due before it answers, and a job leaves the
            gauge only once it has ended (trained and published, or given way)."""
            return vocabulary_jobs(a.url) == vocabulary_jobs(b.url) == 0

        def vocabulary_version() -> int | None:
            with engine.connect() as conn:
                return conn.scalar(
                    select(MapVocabulary.version).where(
                        MapVocabulary.map_id == map_id,
                        MapVocabulary.feature_model == feature_model,
                    )
                )

        # While another holder (this test) has the training lock, neither replica trains,
        # though the map has grown past the training threshold on both.
        with exclusive(engine, f"vocabulary:{map_id}:{feature_model}") as held:
            assert held
            for i, view in enumerate(reference_views[1:MIN_IMAGES]):
                response = upload_view(on_a if i % 2 else on_b, map_id, view)  # type: ignore[arg-type]
                assert response.status_code == 201, response.text  # type: ignore[attr-defined]
                ids.append(response.json()["id"])  # type: ignore[attr-defined]
            for server in (a, b):  # each saw the map due and tried
                assert sorted(localize(server.url, map_id, query_views[0])) == sorted(ids)
                assert wait_until(lambda s=server: "training runs elsewhere" in s.log_text())
            assert wait_until(trainers_idle, 120)  # every training scheduled so far gave way
            assert vocabulary_version() is None

        # Released: an add on each replica at once finds the vocabulary due on both (a
        # localize checks only when the map changed); one trains and publishes.
        with ThreadPoolExecutor(2) as pool:
            both = pool.map(
                lambda pair: upload_view(*pair),  # type: ignore[arg-type]
                [
                    (on_a, map_id, reference_views[MIN_IMAGES]),
                    (on_b, map_id, reference_views[MIN_IMAGES + 1]),
                ],
            )
            ids += [response.json()["id"] for response in both]  # type: ignore[attr-defined]
        # Both trainings have ended: a second one, were there one, has published v2 by now.
        assert wait_until(trainers_idle, 120)
        assert vocabulary_version() == 1, a.log_text() + b.log_text()
        assert a.log_text().count(TRAINED) + b.log_text().count(TRAINED) == 1

        # An add acknowledged by A is retrieved by B's next localize (B's index is warm).
        assert sorted(localize(b.url, map_id, query_views[2])) == sorted(ids)
        added = upload_view(on_a, map_id, reference_views[MIN_IMAGES + 2])  # type: ignore[arg-type]
        assert added.status_code == 201  # type: ignore[attr-defined]
        new_id = added.json()["id"]  # type: ignore[attr-defined]
        assert new_id in localize(b.url, map_id, reference_views[MIN_IMAGES + 2])

        # A delete acknowledged by A is never served by B afterwards.
        assert on_a.delete(f"/v1/maps/{map_id}/images/{new_id}").status_code == 204
        assert on_b.get(f"/v1/maps/{map_id}/images/{new_id}").status_code == 404
        assert new_id not in localize(b.url, map_id, reference_views[MIN_IMAGES + 2])
        assert sorted(localize(b.url, map_id, query_views[3])) == sorted(ids)
    engine.dispose()
