"""Each map's feature configuration: taken by name among those the server serves
(SLLOC_FEATURES and SLLOC_EVALUATION_FEATURES), or (``features: auto``, the default) from its
own self-evaluation, which runs when the map has grown enough and again when it has changed
enough. SQLite and PostgreSQL, real SIFT and the exported XFeat on rendered views with exact
poses."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update

from db.models import Map, MapEvaluation
from db.repositories.evaluations import EvaluationRepository
from services.components import missing_models
from tests.conftest import localize_view, make_client, upload_view
from tests.polling import wait_until
from tools.synthetic.scene import SyntheticView

MODELS = Path(__file__).resolve().parents[2] / "models"
OTHER = "xfeat"  # served besides the server's sift
AUTO_REFERENCES = 6


@pytest.fixture
def client(database_url: str, localizer: Any, tmp_path: Path) -> Iterator[TestClient]:
    if missing_models(MODELS, OTHER):
        pytest.skip(f"{OTHER}'s models are not built (scripts/build_models.sh)")
    settings = {
        "data_dir": tmp_path / "data",
        "features": "sift",
        "models_dir": MODELS,
        "evaluation_features": OTHER,
        "auto_evaluation_references": AUTO_REFERENCES,
    }
    with make_client(database_url, localizer, **settings) as c:
        yield c


def _map(client: TestClient, views: list[SyntheticView], **features: object) -> str:
    body: dict[str, object] = {"name": "scene"}
    if features:
        body["features"] = features
    created = client.post("/v1/maps", json=body)
    assert created.status_code == 201, created.text
    map_id = str(created.json()["id"])
    for view in views:
        assert upload_view(client, map_id, view).status_code == 201
    return map_id


def _settled(client: TestClient, map_id: str) -> dict[str, Any]:
    """The map once it is neither evaluating nor re-describing its references."""

    def body() -> dict[str, Any]:
        answer: dict[str, Any] = client.get(f"/v1/maps/{map_id}").json()
        return answer

    def idle() -> bool:
        client.app.state.evaluator.worker.wait(120.0)  # type: ignore[attr-defined]
        client.app.state.reextractor.worker.wait(120.0)  # type: ignore[attr-defined]
        return bool(body()["features"]["state"] == "ready")

    assert wait_until(idle, timeout_s=240.0)
    return body()


def _position_error_m(client: TestClient, map_id: str, view: SyntheticView) -> float:
    response = localize_view(client, map_id, view)
    assert response.status_code == 200, response.text
    answer = response.json()
    assert answer["localized"], answer
    return float(np.linalg.norm(np.array(answer["camera_center"]) - view.cam_from_world.center))


def _evaluations(client: TestClient, map_id: str) -> list[dict[str, Any]]:
    items: list[dict[str, Any]] = client.get(f"/v1/maps/{map_id}/evaluations").json()["items"]
    return items


def test_a_map_takes_a_configuration_the_server_serves_by_name(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    health = client.get("/v1/health").json()
    assert health["models"]["feature_configurations"] == ["sift", OTHER]
    map_id = _map(client, reference_views[:8], preset=OTHER)
    described = client.get(f"/v1/maps/{map_id}").json()
    assert described["features"]["preset"] == OTHER and not described["features"]["auto"]
    [group] = described["feature_models"]["described_by"]
    assert group["feature_model"].startswith("xfeat-") and group["served"]
    assert _position_error_m(client, map_id, query_views[0]) < 0.05
    # back to the server's own: described anew from the originals, then switched
    patched = client.patch(f"/v1/maps/{map_id}", json={"features": {"preset": "sift"}})
    assert patched.status_code == 200, patched.text
    assert patched.json()["features"]["pending"]["preset"] == "sift"
    after = _settled(client, map_id)
    assert after["features"]["preset"] == "sift"
    [group] = after["feature_models"]["described_by"]
    assert group["feature_model"].startswith("sift-") and group["image_count"] == 8
    assert _position_error_m(client, map_id, query_views[0]) < 0.05
    # a configuration the server does not serve is refused by name, creating or changing
    refused = client.post("/v1/maps", json={"name": "x", "features": {"preset": "aliked"}})
    assert refused.status_code == 422 and "aliked is not served here" in refused.json()["detail"]
    refused = client.patch(f"/v1/maps/{map_id}", json={"features": {"preset": "disk"}})
    assert refused.status_code == 422 and "SLLOC_EVALUATION_FEATURES" in refused.json()["detail"]


def test_a_map_that_follows_its_evaluation_takes_the_configuration_recommended(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    map_id = _map(client, reference_views[: AUTO_REFERENCES - 1])
    created = client.get(f"/v1/maps/{map_id}").json()["features"]
    assert created["auto"] and created["preset"] == "sift"  # the server's until evaluated
    client.app.state.evaluator.worker.wait(60.0)  # type: ignore[attr-defined]
    assert _evaluations(client, map_id) == []  # not enough references yet
    assert upload_view(client, map_id, reference_views[AUTO_REFERENCES]).status_code == 201
    after = _settled(client, map_id)
    [evaluation] = _evaluations(client, map_id)
    assert evaluation["state"] == "done", evaluation
    assert evaluation["request"]["configurations"] == ["sift", OTHER]
    recommended = evaluation["result"]["recommended"]
    assert recommended in ("sift", OTHER)
    assert after["features"]["preset"] == recommended and after["features"]["auto"]
    [group] = after["feature_models"]["described_by"]
    assert group["feature_model"].startswith(f"{recommended}-")
    assert _position_error_m(client, map_id, query_views[0]) < 0.05
    # one more reference is not change enough; ten adds and deletes that replace references
    # are, once ten minutes have passed since the last evaluation started
    assert upload_view(client, map_id, reference_views[AUTO_REFERENCES + 1]).status_code == 201
    _settled(client, map_id)
    assert len(_evaluations(client, map_id)) == 1
    images = client.get(f"/v1/maps/{map_id}/images").json()["items"]
    replacements = reference_views[AUTO_REFERENCES + 2 : AUTO_REFERENCES + 7]
    for image, view in zip(images[:5], replacements, strict=True):
        assert client.delete(f"/v1/maps/{map_id}/images/{image['id']}").status_code == 204
        assert upload_view(client, map_id, view).status_code == 201
    _settled(client, map_id)
    assert len(_evaluations(client, map_id)) == 1
    sessions = client.app.state.sessions  # type: ignore[attr-defined]
    with sessions.begin() as session:
        session.execute(
            update(MapEvaluation).values(created_at=datetime.now(UTC) - timedelta(seconds=601))
        )
    [image, *_] = client.get(f"/v1/maps/{map_id}/images").json()["items"]
    assert client.delete(f"/v1/maps/{map_id}/images/{image['id']}").status_code == 204
    _settled(client, map_id)
    assert len(_evaluations(client, map_id)) == 2
    # a map that grew by a quarter is evaluated at once
    for view in reference_views[AUTO_REFERENCES + 7 : AUTO_REFERENCES + 17]:
        assert upload_view(client, map_id, view).status_code == 201
    current = _settled(client, map_id)["features"]["preset"]
    assert len(_evaluations(client, map_id)) == 3
    # naming a configuration stops following; auto follows again (evaluated when due)
    named = client.patch(f"/v1/maps/{map_id}", json={"features": {"preset": current}})
    assert named.status_code == 200 and not named.json()["features"]["auto"]
    auto = client.patch(f"/v1/maps/{map_id}", json={"features": {"preset": "auto"}})
    assert auto.status_code == 200 and auto.json()["features"]["auto"]
    assert auto.json()["features"]["preset"] == current


def test_a_map_due_an_evaluation_when_it_switches_never_reads_ready_before_it(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    """The evaluation a map is due when its references switch to another configuration is
    stored in the switch's own transaction: by the time anything after the switch runs, the
    map already reads evaluating (it used to read ready until that evaluation was queued)."""
    map_id = _map(client, reference_views[: AUTO_REFERENCES - 1])
    state = client.app.state  # type: ignore[attr-defined]
    state.evaluator.worker.wait(60.0)
    assert _evaluations(client, map_id) == []
    evaluating_at_switch: list[bool] = []
    switched = state.reextractor.on_switch

    def recording(switched_map: str, localizer: Any) -> None:
        with state.sessions() as session:
            active = EvaluationRepository(session).evaluating([switched_map])
        evaluating_at_switch.append(switched_map in active)
        switched(switched_map, localizer)

    state.reextractor.on_switch = recording
    # the map re-describes its references with the other configuration, following its
    # evaluation still, and is due one as it switches
    state.evaluator.auto.min_references = AUTO_REFERENCES - 1
    with state.sessions.begin() as session:
        session.execute(
            update(Map).where(Map.id == map_id).values(pending_preset=OTHER, reextracting=True)
        )
    state.reextractor.schedule(map_id)
    after = _settled(client, map_id)
    # (a second switch may follow, to the configuration that evaluation recommends: the map
    # was just evaluated and is not due another)
    assert evaluating_at_switch[0], evaluating_at_switch
    evaluations = _evaluations(client, map_id)
    assert [e["state"] for e in evaluations] == ["done"], evaluations
    assert evaluations[0]["result"]["served"] == OTHER
    assert after["features"]["auto"]
    assert after["features"]["preset"] == evaluations[0]["result"]["recommended"]


def test_a_map_whose_configuration_is_not_served_says_so(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    """A server restarted without the configuration a map chose: the map, health and
    localize name it and the setting that serves it, never ``no_references``."""
    map_id = _map(client, reference_views[:8], preset="sift")
    sessions = client.app.state.sessions  # type: ignore[attr-defined]
    with sessions.begin() as session:
        session.execute(update(Map).where(Map.id == map_id).values(feature_preset="aliked"))
    body = client.get(f"/v1/maps/{map_id}").json()
    assert body["features"]["preset"] == "aliked"
    assert not body["feature_models"]["servable"]
    assert "aliked is not served here" in body["feature_models"]["detail"]
    refused = localize_view(client, map_id, query_views[0])
    assert refused.status_code == 409
    assert "SLLOC_EVALUATION_FEATURES" in refused.json()["detail"]
    added = upload_view(client, map_id, reference_views[9])
    assert added.status_code == 409  # type: ignore[attr-defined]
    client.app.state.unservable_survey = None  # type: ignore[attr-defined]
    health = client.get("/v1/health").json()
    assert health["status"] == "degraded" and health["unservable_map_count"] == 1
    # following the evaluation again: served with the server's configuration until evaluated
    # (its references, described by sift, need no new description)
    auto = client.patch(f"/v1/maps/{map_id}", json={"features": {"preset": "auto"}})
    assert auto.status_code == 200, auto.text
    after = auto.json()  # and evaluated, being large enough
    assert (after["features"]["preset"], after["features"]["state"]) == ("sift", "evaluating")
    assert after["features"]["auto"] and after["feature_models"]["servable"]
    _settled(client, map_id)
    assert _position_error_m(client, map_id, query_views[0]) < 0.05
