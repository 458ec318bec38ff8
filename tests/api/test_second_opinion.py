"""A second opinion: a query its map's feature configuration retrieves references for but does
not localize is localized again by the server's second configuration, against those
references described from their originals. SQLite and PostgreSQL, real SIFT and the exported
XFeat on rendered views with exact poses; the map's own configuration is starved (8 SIFT
keypoints an image) so that it cannot answer."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.components import missing_models
from services.geometry.rigid import Rigid3d
from tests.conftest import image_metadata, make_client, upload_view
from tools.synthetic.scene import SyntheticView, encode_png, unrelated_image

MODELS = Path(__file__).resolve().parents[2] / "models"
OTHER = "xfeat"  # served besides the server's sift
REFERENCES = 6


def _client(database_url: str, localizer: Any, tmp_path: Path, second_opinion: str) -> TestClient:
    if missing_models(MODELS, OTHER):
        pytest.skip(f"{OTHER}'s models are not built (scripts/build_models.sh)")
    return make_client(
        database_url,
        localizer,
        data_dir=tmp_path / "data",
        features="sift",
        models_dir=MODELS,
        evaluation_features=OTHER,
        second_opinion=second_opinion,
    )


@pytest.fixture
def client(database_url: str, localizer: Any, tmp_path: Path) -> Iterator[TestClient]:
    with _client(database_url, localizer, tmp_path, "auto") as c:
        yield c


def _starved_map(client: TestClient, views: list[SyntheticView]) -> str:
    """A sift map of ``views`` at 8 keypoints an image: its matches cannot verify a pose."""
    created = client.post(
        "/v1/maps", json={"name": "scene", "features": {"preset": "sift", "max_keypoints": 8}}
    )
    assert created.status_code == 201, created.text
    map_id = str(created.json()["id"])
    for view in views:
        assert upload_view(client, map_id, view).status_code == 201
    return map_id


def _localize(client: TestClient, map_id: str, view: SyntheticView, **params: object) -> Any:
    camera = image_metadata(view)["camera"]
    response = client.post(
        f"/v1/maps/{map_id}/localize",
        files={"image": ("q.png", encode_png(view.image), "image/png")},
        data={"params": json.dumps({"camera": camera, **params})},
    )
    assert response.status_code == 200, response.text
    return response.json()


def _error_m(answer: dict[str, Any], view: SyntheticView) -> float:
    return float(np.linalg.norm(np.array(answer["camera_center"]) - view.cam_from_world.center))


def test_a_query_the_map_cannot_localize_gets_a_second_opinion(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    map_id = _starved_map(client, reference_views[:REFERENCES])
    query = query_views[0]
    alone = _localize(client, map_id, query, second_opinion=False)
    assert not alone["localized"] and alone["second_opinion"] is None, alone
    retrieved = len(alone["retrieved"])
    assert retrieved > 0

    answer = _localize(client, map_id, query)
    assert answer["localized"], answer
    assert _error_m(answer, query) < 0.05
    opinion = answer["second_opinion"]
    assert opinion["features"] == OTHER and opinion["localized"]
    assert opinion["described"] == retrieved
    assert answer["confidence"] == opinion["confidence"]
    assert answer["timings_ms"]["total"] >= opinion["elapsed_ms"]
    # the references described are kept: the next query describes none again
    again = _localize(client, map_id, query)
    assert again["localized"] and again["second_opinion"]["described"] == 0
    assert _error_m(again, query) < 0.05
    # what the map stores is unchanged: its own configuration, its references
    described = client.get(f"/v1/maps/{map_id}").json()
    assert described["features"]["preset"] == "sift" and described["image_count"] == REFERENCES
    metrics = client.get("/metrics").text
    assert 'slloc_localize_second_opinions_total{features="xfeat",localized="true"} 2.0' in metrics


def test_an_image_of_nothing_in_the_map_asks_none(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    """Its pose search runs to its cap of hypotheses, finding no pose a few percent of the
    matches agree with: another configuration is not asked."""
    created = client.post("/v1/maps", json={"name": "scene", "features": {"preset": "sift"}})
    assert created.status_code == 201, created.text
    map_id = str(created.json()["id"])
    for view in reference_views[:REFERENCES]:
        assert upload_view(client, map_id, view).status_code == 201
    camera = image_metadata(reference_views[0])["camera"]
    for seed in range(3):
        response = client.post(
            f"/v1/maps/{map_id}/localize",
            files={"image": ("q.png", encode_png(unrelated_image(seed)), "image/png")},
            data={"params": json.dumps({"camera": camera})},
        )
        assert response.status_code == 200, response.text
        answer = response.json()
        # failures a second opinion is asked for elsewhere (asked here, it says it answered
        # no better, after 1.5-2.5 s)
        assert answer["reason"] in ("no_consensus", "degenerate_geometry"), answer
        assert answer["second_opinion"] is None, answer


def test_a_second_opinion_below_the_confidence_asked_is_no_answer(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    map_id = _starved_map(client, reference_views[:REFERENCES])
    answer = _localize(client, map_id, query_views[0], min_confidence=1.0)
    assert not answer["localized"] and answer["cam_from_world"] is None, answer
    opinion = answer["second_opinion"]
    assert opinion["features"] == OTHER and not opinion["localized"]
    assert opinion["reason"] == "low_confidence"


def test_two_withheld_poses_that_agree_say_so(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    """Both configurations find the query's pose, each below the confidence asked (1.0): the
    two agree, and the answer is still withheld at the more confident one's confidence."""
    created = client.post("/v1/maps", json={"name": "scene", "features": {"preset": "sift"}})
    map_id = str(created.json()["id"])
    for view in reference_views[:REFERENCES]:
        assert upload_view(client, map_id, view).status_code == 201
    query = query_views[0]
    answer = _localize(client, map_id, query, min_confidence=1.0)
    assert not answer["localized"] and answer["reason"] == "low_confidence", answer
    opinion = answer["second_opinion"]
    assert opinion["features"] == OTHER and opinion["reason"] == "low_confidence"
    assert opinion["agreed"], opinion
    assert answer["confidence"] >= opinion["confidence"]
    pose = answer["candidate"]
    candidate = Rigid3d.from_quaternion(np.array(pose["rotation"]), np.array(pose["translation"]))
    assert np.linalg.norm(candidate.center - query.cam_from_world.center) < 0.05
    metrics = client.get("/metrics").text
    assert 'slloc_localize_agreed_opinions_total{features="xfeat",localized="false"} 1.0' in metrics


def test_a_map_served_well_asks_no_second_opinion(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    created = client.post("/v1/maps", json={"name": "scene", "features": {"preset": "sift"}})
    map_id = str(created.json()["id"])
    for view in reference_views[:REFERENCES]:
        assert upload_view(client, map_id, view).status_code == 201
    answer = _localize(client, map_id, query_views[0])
    assert answer["localized"] and answer["second_opinion"] is None, answer


def test_a_server_without_a_second_configuration_answers_at_once(
    database_url: str,
    localizer: Any,
    tmp_path: Path,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    with _client(database_url, localizer, tmp_path, "") as client:
        map_id = _starved_map(client, reference_views[:REFERENCES])
        answer = _localize(client, map_id, query_views[0])
        assert not answer["localized"] and answer["second_opinion"] is None, answer


def test_an_unknown_second_configuration_is_refused_at_start_up(
    database_url: str, localizer: Any, tmp_path: Path
) -> None:
    with pytest.raises(ValueError, match="second_opinion"):
        _client(database_url, localizer, tmp_path, "surf")
