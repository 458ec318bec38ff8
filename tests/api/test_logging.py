"""Request ids and structured logs: every answer and every log record of a request carry its
id; no user string can start a log line of its own (issue #14, defect 12)."""

from __future__ import annotations

import json
import logging
import re
import sys

import pytest
from fastapi.testclient import TestClient

from app.api.deps import get_localizers
from app.logs import JsonFormatter, TextFormatter
from services.components import Localizers
from services.localization.localizer import Localizer
from tests.conftest import create_map, make_client, upload_view
from tools.synthetic.scene import SyntheticView

GENERATED_ID = re.compile(r"[0-9a-f]{32}")
# a path segment that, written raw, would put a forged record on a line of its own
FORGING_PATH = "/v1/maps/x%0A2024-01-01 00:00:00,000 ERROR forged: admin key leaked"


def _access_record(caplog: pytest.LogCaptureFixture, request_id: str) -> logging.LogRecord:
    (record,) = (
        r
        for r in caplog.records
        if r.name == "slloc.access" and getattr(r, "request_id", None) == request_id
    )
    return record


def test_every_answer_carries_a_generated_request_id(client: TestClient) -> None:
    first = client.get("/v1/health").headers["X-Request-ID"]
    second = client.get("/v1/health").headers["X-Request-ID"]
    assert GENERATED_ID.fullmatch(first)
    assert GENERATED_ID.fullmatch(second)
    assert first != second


def test_a_safe_request_id_is_echoed(client: TestClient) -> None:
    response = client.get("/v1/health", headers={"X-Request-ID": "Trace-42.a_b"})
    assert response.headers["X-Request-ID"] == "Trace-42.a_b"


@pytest.mark.parametrize("unsafe", ["", "has space", "a/b", "x" * 65, "quote\"'"])
def test_an_unsafe_request_id_is_replaced(client: TestClient, unsafe: str) -> None:
    response = client.get("/v1/health", headers={"X-Request-ID": unsafe})
    assert GENERATED_ID.fullmatch(response.headers["X-Request-ID"])


def test_problem_documents_carry_the_request_id(client: TestClient) -> None:
    response = client.get("/v1/maps/unknown", headers={"X-Request-ID": "req-404"})
    assert response.status_code == 404
    assert response.headers["X-Request-ID"] == "req-404"
    assert response.json()["request_id"] == "req-404"

    response = client.post("/v1/maps", json={"name": ""})
    assert response.status_code == 422
    assert response.json()["request_id"] == response.headers["X-Request-ID"]


def test_middleware_answers_carry_the_request_id(database_url: str, localizer: Localizer) -> None:
    with make_client(
        database_url, localizer, api_keys="adm-secret:admin", max_upload_bytes=1000
    ) as c:
        unauthorized = c.post("/v1/maps", json={"name": "m"}, headers={"X-Request-ID": "r401"})
        assert unauthorized.status_code == 401
        assert unauthorized.headers["X-Request-ID"] == "r401"
        assert unauthorized.json()["request_id"] == "r401"

        too_large = c.post(
            "/v1/maps",
            content=b"x" * (3 * 1024 * 1024),
            headers={"X-API-Key": "adm-secret", "X-Request-ID": "r413"},
        )
        assert too_large.status_code == 413
        assert too_large.headers["X-Request-ID"] == "r413"
        assert too_large.json()["request_id"] == "r413"


def test_a_500_carries_the_request_id_and_logs_it(
    database_url: str, localizer: Localizer, caplog: pytest.LogCaptureFixture
) -> None:
    def broken() -> Localizers:
        raise RuntimeError("boom")

    caplog.set_level(logging.INFO)
    with make_client(database_url, localizer, raise_server_exceptions=False) as c:
        c.app.dependency_overrides[get_localizers] = broken  # type: ignore[attr-defined]
        response = c.get("/v1/health", headers={"X-Request-ID": "r500"})
    assert response.status_code == 500
    assert response.headers["X-Request-ID"] == "r500"
    assert response.json()["request_id"] == "r500"
    assert _access_record(caplog, "r500").status == 500  # type: ignore[attr-defined]
    (error,) = (r for r in caplog.records if r.name == "app.errors")
    assert error.request_id == "r500"  # type: ignore[attr-defined]


def test_records_of_an_add_carry_its_request_id(
    client: TestClient,
    reference_views: list[SyntheticView],
    caplog: pytest.LogCaptureFixture,
) -> None:
    map_id = create_map(client)
    caplog.set_level(logging.INFO)
    response = upload_view(client, map_id, reference_views[0])
    assert response.status_code == 201  # type: ignore[attr-defined]
    request_id = response.headers["X-Request-ID"]  # type: ignore[attr-defined]

    (added,) = (r for r in caplog.records if r.name == "app.usecases.images")
    assert added.request_id == request_id  # type: ignore[attr-defined]
    access = _access_record(caplog, request_id)
    assert added.thread != access.thread  # logged on a worker thread
    assert access.method == "POST"  # type: ignore[attr-defined]
    assert access.path == f"/v1/maps/{map_id}/images"  # type: ignore[attr-defined]
    assert access.status == 201  # type: ignore[attr-defined]
    assert access.duration_ms > 0  # type: ignore[attr-defined]
    # no record of the request is without its id
    assert all(
        r.request_id == request_id  # type: ignore[attr-defined]
        for r in caplog.records
        if r.name.startswith(("app.", "services.", "db.", "slloc."))
        and r.thread in (added.thread, access.thread)
    )


def _forging_record(client: TestClient, caplog: pytest.LogCaptureFixture) -> logging.LogRecord:
    caplog.set_level(logging.INFO)
    response = client.get(FORGING_PATH)
    assert response.status_code == 404
    record = _access_record(caplog, response.headers["X-Request-ID"])
    assert "\n" in record.getMessage()  # the decoded path holds the newline
    return record


def test_json_lines_keep_a_forging_string_on_one_line(
    client: TestClient, caplog: pytest.LogCaptureFixture
) -> None:
    record = _forging_record(client, caplog)
    line = JsonFormatter().format(record)
    assert "\n" not in line
    document = json.loads(line)
    assert document["message"] == record.getMessage()
    assert document["path"] == "/v1/maps/x\n2024-01-01 00:00:00,000 ERROR forged: admin key leaked"
    assert document["request_id"] == record.request_id  # type: ignore[attr-defined]
    assert document["level"] == "INFO"
    assert document["logger"] == "slloc.access"
    assert document["method"] == "GET"
    assert document["status"] == 404
    assert isinstance(document["duration_ms"], float)
    assert {"time"} <= document.keys()


def test_text_lines_escape_a_forging_string(
    client: TestClient, caplog: pytest.LogCaptureFixture
) -> None:
    record = _forging_record(client, caplog)
    line = TextFormatter().format(record)
    assert "\n" not in line
    assert f"INFO slloc.access [{record.request_id}]: GET /v1/maps/x\\n2024" in line  # type: ignore[attr-defined]


def test_text_lines_indent_a_traceback() -> None:
    try:
        raise ValueError("line one\nERROR forged")
    except ValueError:
        record = logging.getLogger("t").makeRecord(
            "t", logging.ERROR, __file__, 1, "failed\r\x1b[2J", None, sys.exc_info()
        )
    # the record factory of the app adds request_id; a record made outside a request has None
    lines = TextFormatter().format(record).splitlines()
    assert lines[0].endswith("ERROR t: failed\\r\\x1b[2J")
    assert all(line.startswith("    ") for line in lines[1:])
    assert any("ERROR forged" in line for line in lines[1:])


def test_numpy_warnings_come_out_as_json_lines() -> None:
    """A RuntimeWarning from numpy goes through logging (``py.warnings``), so the JSON log
    format holds for it too instead of a raw two-line stderr message."""
    import subprocess

    script = (
        "import numpy as np\n"
        "from app.logs import configure_logging\n"
        "configure_logging('json')\n"
        "np.log(np.zeros(1))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True
    )
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert lines, done.stderr
    documents = [json.loads(line) for line in lines]
    assert any(
        d["logger"] == "py.warnings" and "divide by zero" in d["message"] for d in documents
    ), documents
