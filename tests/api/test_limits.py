"""Cost limits (issue #14): feature options bounded by settings, a time budget per localize,
and admission control for localize and add (a bounded queue, then 503 with Retry-After)."""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from app.admission import Admission
from app.errors import ProblemError
from services.localization.localizer import Localizer
from services.runtime.worker_slots import WorkerSlots
from tests.conftest import create_map, make_client, upload_view
from tools.synthetic.scene import SyntheticView, encode_png

PROBLEM = "application/problem+json"


def _localize(
    client: TestClient, map_id: str, view: SyntheticView, params: dict[str, object]
) -> object:
    return client.post(
        f"/v1/maps/{map_id}/localize",
        files={"image": ("q.png", encode_png(view.image), "image/png")},
        data={"params": json.dumps(params)},
    )


@pytest.mark.parametrize(
    ("features", "fragment"),
    [
        ({"max_keypoints": 4097}, "features.max_keypoints may be at most 4096"),
        ({"max_side": 1025}, "features.max_side may be at most 1024"),
    ],
)
def test_feature_options_above_the_settings_are_422(
    client: TestClient, features: dict[str, int], fragment: str
) -> None:
    response = client.post("/v1/maps", json={"name": "big", "features": features})
    assert response.status_code == 422
    assert response.headers["content-type"] == PROBLEM
    assert fragment in response.json()["detail"]
    assert client.get("/v1/maps").json()["total"] == 0
    at_limit = {"max_keypoints": 4096, "max_side": 1024}
    assert client.post("/v1/maps", json={"name": "ok", "features": at_limit}).status_code == 201


def test_feature_limits_follow_the_settings(database_url: str, localizer: Localizer) -> None:
    with make_client(database_url, localizer, max_keypoints=500, max_side=640) as c:
        over = c.post("/v1/maps", json={"name": "m", "features": {"max_keypoints": 501}})
        assert over.status_code == 422
        within = {"max_keypoints": 500, "max_side": 640}
        assert c.post("/v1/maps", json={"name": "m", "features": within}).status_code == 201


def test_spent_time_budget_is_time_budget_exceeded(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    map_id = create_map(client)
    for view in reference_views[:3]:
        assert upload_view(client, map_id, view).status_code == 201  # type: ignore[attr-defined]
    response = _localize(client, map_id, query_views[0], {"time_budget_s": 1e-6})
    assert response.status_code == 200, response.text  # type: ignore[attr-defined]
    result = response.json()  # type: ignore[attr-defined]
    assert result["localized"] is False
    assert result["reason"] == "time_budget_exceeded"
    assert result["cam_from_world"] is None
    assert set(result["timings_ms"]) == {
        "decode",
        "extract",
        "retrieve",
        "match",
        "estimate",
        "total",
    }


def test_time_budget_above_the_setting_is_422(
    database_url: str, localizer: Localizer, query_views: list[SyntheticView]
) -> None:
    with make_client(database_url, localizer, localize_time_budget_s=2.0) as c:
        map_id = create_map(c)
        response = _localize(c, map_id, query_views[0], {"time_budget_s": 2.5})
        assert response.status_code == 422  # type: ignore[attr-defined]
        assert "time_budget_s may be at most 2.0" in response.json()["detail"]  # type: ignore[attr-defined]
        for bad in (0, -1, "soon"):
            assert _localize(c, map_id, query_views[0], {"time_budget_s": bad}).status_code == 422  # type: ignore[attr-defined]


@pytest.fixture
def one_worker(database_url: str, localizer: Localizer) -> Iterator[TestClient]:
    with make_client(database_url, localizer, localize_workers=1, max_queued=0) as c:
        yield c


def _assert_busy(response: object) -> None:
    assert response.status_code == 503, response.text  # type: ignore[attr-defined]
    assert response.headers["content-type"] == PROBLEM  # type: ignore[attr-defined]
    assert response.headers["retry-after"] == "1"  # type: ignore[attr-defined]
    assert response.json()["type"].endswith("/service-busy")  # type: ignore[attr-defined]


def test_full_queue_refuses_localize_and_add_with_503(
    one_worker: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    map_id = create_map(one_worker)
    admission: Admission = one_worker.app.state.admission  # type: ignore[attr-defined]
    with admission.admit():  # the one worker is taken and nothing may wait
        _assert_busy(_localize(one_worker, map_id, query_views[0], {}))
        _assert_busy(upload_view(one_worker, map_id, reference_views[0]))
        assert one_worker.get(f"/v1/maps/{map_id}").json()["image_count"] == 0
        assert one_worker.get("/v1/health").status_code == 200
    assert upload_view(one_worker, map_id, reference_views[0]).status_code == 201  # type: ignore[attr-defined]
    assert _localize(one_worker, map_id, query_views[0], {}).status_code == 200  # type: ignore[attr-defined]


def test_a_refused_request_is_not_read(
    database_url: str, localizer: Localizer, reference_views: list[SyntheticView]
) -> None:
    """Admission comes before the uploads are read into memory (the memory bound counts
    the uploads of admitted requests only): over its upload limit but busy, a request is
    503, not 413."""
    small = {"localize_workers": 1, "max_queued": 0, "max_upload_bytes": 1000}
    with make_client(database_url, localizer, **small) as c:
        map_id = create_map(c)
        admission: Admission = c.app.state.admission  # type: ignore[attr-defined]
        with admission.admit():
            _assert_busy(upload_view(c, map_id, reference_views[0]))
        too_large = upload_view(c, map_id, reference_views[0])
        assert too_large.status_code == 413, too_large.text  # type: ignore[attr-defined]


def test_queued_requests_are_admitted_up_to_the_bound() -> None:
    admission = Admission(WorkerSlots(1, memory_mib=100.0), queued=1)
    with admission.admit(), admission.admit():
        with pytest.raises(ProblemError) as refused, admission.admit():
            pass
        assert refused.value.status == 503
    with admission.admit(), admission.admit():
        pass
