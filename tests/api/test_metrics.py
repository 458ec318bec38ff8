"""GET /metrics: scraped after real requests and parsed with the Prometheus client's own
parser; the series are checked against what the requests did."""

from __future__ import annotations

import json
import uuid

import cv2
import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families
from prometheus_client.samples import Sample

from app.settings import Settings
from services.localization.localizer import Localizer
from services.localization.widen import SURE_CONFIDENCE
from tests.conftest import create_map, image_metadata, make_client, upload_view
from tools.synthetic.scene import SyntheticView, encode_png, unrelated_image

LOCALIZE_ROUTE = "/v1/maps/{map_id}/localize"
STAGES = ("decode", "extract", "retrieve", "match", "estimate", "total")


def scrape(client: TestClient, **kwargs: object) -> dict[str, list[Sample]]:
    response = client.get("/metrics", **kwargs)  # type: ignore[arg-type]
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith("text/plain; version=")
    return {f.name: f.samples for f in text_string_to_metric_families(response.text)}


def value(samples: list[Sample], name: str, **labels: str) -> float:
    found = [s.value for s in samples if s.name == name and labels.items() <= s.labels.items()]
    assert len(found) == 1, (name, labels, [s for s in samples if s.name == name])
    return found[0]


def localize(
    client: TestClient, map_id: str, view: SyntheticView, image: bytes | None = None
) -> dict[str, object]:
    """``view`` (or ``image`` in its camera) as a query."""
    params = {"camera": image_metadata(view)["camera"]}
    upload = encode_png(view.image) if image is None else image
    response = client.post(
        f"/v1/maps/{map_id}/localize",
        files={"image": (view.name, upload, "image/png")},
        data={"params": json.dumps(params)},
    )
    assert response.status_code == 200, response.text
    result: dict[str, object] = response.json()
    return result


def test_queries_retrieved_again_wider_are_counted(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    """An answer that is unsure after its first retrieval (a query blurred until its
    confidence falls below ``SURE_CONFIDENCE``) on a map of more references than top_k is
    retrieved again wider, says so and is counted; a sure one is not, nor an unrelated image
    (its pose search drew every hypothesis without a pose: no spread of references helps)."""
    map_id = create_map(client)
    for view in reference_views:
        assert upload_view(client, map_id, view).status_code == 201
    answers = [localize(client, map_id, view) for view in query_views[:3]]
    blurred = cv2.GaussianBlur(query_views[1].image, (0, 0), 6)
    unsure = localize(client, map_id, query_views[1], encode_png(blurred))
    assert unsure["wider_retrieval"] is True, unsure
    unrelated = localize(client, map_id, query_views[0], encode_png(unrelated_image(0)))
    assert unrelated["localized"] is False and unrelated["wider_retrieval"] is False
    for answer in answers:
        confidence = answer["confidence"]
        assert isinstance(confidence, float)
        sure = answer["localized"] is True and confidence >= SURE_CONFIDENCE
        assert answer["wider_retrieval"] is not sure
    assert any(answer["wider_retrieval"] is False for answer in answers)
    widened = sum(answer["wider_retrieval"] is True for answer in [*answers, unsure, unrelated])
    counted = scrape(client)["slloc_localize_wider_retrievals"]
    assert value(counted, "slloc_localize_wider_retrievals_total") == widened


def test_metrics_after_localize(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    map_id = create_map(client)
    for view in reference_views[:8]:
        assert upload_view(client, map_id, view).status_code == 201
    result = localize(client, map_id, query_views[0])
    assert result["localized"] is True
    empty = create_map(client, "empty")
    failed = localize(client, empty, query_views[0])
    assert failed["reason"] == "no_references"
    assert client.get(f"/v1/maps/{uuid.uuid4()}").status_code == 404
    assert client.get("/no/such/path").status_code == 404

    metrics = scrape(client)

    requests = metrics["slloc_http_requests"]
    assert value(requests, "slloc_http_requests_total", route=LOCALIZE_ROUTE, status="200") == 2
    assert value(requests, "slloc_http_requests_total", route="/v1/maps/{map_id}/images") == 8
    assert value(requests, "slloc_http_requests_total", route="/v1/maps/{map_id}") == 1
    assert value(requests, "slloc_http_requests_total", route="unmatched", status="404") == 1
    # route templates only: no id ever becomes a label value
    labels = {v for s in requests for v in s.labels.values()}
    assert not any(map_id in v or empty in v for v in labels)

    latency = metrics["slloc_http_request_duration_seconds"]
    count = value(latency, "slloc_http_request_duration_seconds_count", route=LOCALIZE_ROUTE)
    assert count == 2
    buckets = sorted(
        (float(s.labels["le"]), s.value)
        for s in latency
        if s.name.endswith("_bucket") and s.labels["route"] == LOCALIZE_ROUTE
    )
    assert [b for _, b in buckets] == sorted(b for _, b in buckets)  # cumulative
    assert buckets[-1] == (float("inf"), count)
    assert value(latency, "slloc_http_request_duration_seconds_sum", route=LOCALIZE_ROUTE) > 0

    stages = metrics["slloc_localize_stage_seconds"]
    timings = result["timings_ms"]
    assert isinstance(timings, dict)
    for stage in STAGES:
        # both requests ran every stage (the one on the empty map matched nothing)
        assert value(stages, "slloc_localize_stage_seconds_count", stage=stage) == 2
        assert value(stages, "slloc_localize_stage_seconds_sum", stage=stage) >= (
            timings[stage] / 1000.0 - 1e-6
        )

    outcomes = metrics["slloc_localize_outcomes"]
    assert value(outcomes, "slloc_localize_outcomes_total", localized="true", reason="none") == 1
    # 8 references, no more than top_k: a wider retrieval brings no other
    assert result["wider_retrieval"] is False and failed["wider_retrieval"] is False
    assert (
        value(metrics["slloc_localize_wider_retrievals"], "slloc_localize_wider_retrievals_total")
        == 0
    )
    assert (
        value(outcomes, "slloc_localize_outcomes_total", localized="false", reason="no_references")
        == 1
    )

    maps = metrics["slloc_map_images"]
    assert value(maps, "slloc_map_images", map_id=map_id, map="scene") == 8
    assert value(maps, "slloc_map_images", map_id=empty, map="empty") == 0
    assert (
        value(metrics["slloc_retrieval_cache_references"], "slloc_retrieval_cache_references") >= 8
    )
    assert value(metrics["slloc_retrieval_cache_bytes"], "slloc_retrieval_cache_bytes") > 0
    assert value(metrics["slloc_database_up"], "slloc_database_up") == 1
    assert value(metrics["slloc_blob_store_up"], "slloc_blob_store_up") == 1
    workers = client.get("/v1/health").json()["runtime"]["localize_workers"]
    capacity = value(metrics["slloc_admission_capacity"], "slloc_admission_capacity")
    assert capacity == workers + Settings().max_queued
    assert value(metrics["slloc_admission_admitted"], "slloc_admission_admitted") == 0
    assert value(metrics["slloc_admission_queue_depth"], "slloc_admission_queue_depth") == 0
    jobs = metrics["slloc_background_jobs"]
    for kind in ("vocabulary", "retrieval index"):
        assert value(jobs, "slloc_background_jobs", kind=kind) == 0


@pytest.mark.parametrize("require_key", [False, True])
def test_metrics_access_with_auth_on(
    database_url: str, localizer: Localizer, require_key: bool
) -> None:
    keys = "admin-key:admin,client-key:client"
    with make_client(
        database_url, localizer, api_keys=keys, metrics_require_key=require_key
    ) as client:
        refused = client.post(f"/v1/maps/{uuid.uuid4()}/localize")
        assert refused.status_code == 401
        response = client.get("/metrics")
        if require_key:
            assert response.status_code == 401
            assert response.headers["content-type"] == "application/problem+json"
            assert client.get("/metrics", headers={"X-API-Key": "nope"}).status_code == 401
            metrics = scrape(client, headers={"X-API-Key": "client-key"})
        else:
            metrics = scrape(client)
        requests = metrics["slloc_http_requests"]
        # answered by the key gate before routing, still counted under its route template
        assert value(requests, "slloc_http_requests_total", route=LOCALIZE_ROUTE) == 1


def test_process_and_python_series(client: TestClient) -> None:
    """The process collector's series (and the interpreter's and its GC's) are on /metrics, as
    on the default registry, though the app keeps a registry of its own."""
    families = scrape(client)
    assert value(families["process_resident_memory_bytes"], "process_resident_memory_bytes") > 0
    assert value(families["process_cpu_seconds"], "process_cpu_seconds_total") > 0
    assert value(families["process_open_fds"], "process_open_fds") > 0
    assert value(families["process_start_time_seconds"], "process_start_time_seconds") > 0
    assert value(families["python_info"], "python_info", implementation="CPython") == 1.0
    collected = families["python_gc_objects_collected"]
    assert {s.labels["generation"] for s in collected} == {"0", "1", "2"}
