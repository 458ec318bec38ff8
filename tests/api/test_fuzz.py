"""A bounded fuzz run over the OpenAPI document, on SQLite and PostgreSQL, with auth on.

Every answer must be no server error, of a documented status code, content type and headers,
and of the documented body schema; input the schema forbids must be refused. The budget is
fixed and the generation derandomized, so a run is the same everywhere."""

from __future__ import annotations

import itertools
import json
import zlib
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import dataclass
from typing import Any

import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from schemathesis.checks import not_a_server_error
from schemathesis.python.asgi import ASGIClient
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    negative_data_rejection,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
    unsupported_method,
)

from app.main import create_app
from app.settings import Settings
from services.localization.localizer import Localizer
from tests.conftest import fresh_postgres_database, make_client, upload_view
from tools.synthetic.scene import SyntheticView, encode_png

ADMIN_KEY = "fuzz-admin"
ADMIN = {"X-API-Key": ADMIN_KEY}
BASE_URL = "http://testserver"
# the budget: generated cases per operation (besides schemathesis' boundary cases), and per
# JSON form field; both databases together take about a minute on two cores
MAX_EXAMPLES = 100
MAX_FORM_EXAMPLES = 40
FUZZ_SETTINGS = settings(
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=list(HealthCheck),
)

# the admin key on every case, except those generated without a key (they must get 401)
CONFIG = schemathesis.Config.from_dict(
    {"auth": {"openapi": {"APIKeyHeader": {"api_key": ADMIN_KEY}}}}
)
DOCUMENT = create_app(Settings(database_url="sqlite://")).openapi()


def _without_binary_format(node: object) -> object:
    """The document with ``format: binary`` left out of file fields: schemathesis's coverage
    phase cannot generate it (``Unsupported type: 'Binary'``); ``contentMediaType`` still
    marks them as bytes."""
    if isinstance(node, dict):
        return {
            k: _without_binary_format(v)
            for k, v in node.items()
            if not (k == "format" and v == "binary")
        }
    if isinstance(node, list):
        return [_without_binary_format(v) for v in node]
    return node


schema = schemathesis.openapi.from_dict(_without_binary_format(DOCUMENT), config=CONFIG)

CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
    negative_data_rejection,
    unsupported_method,
]


@dataclass
class Target:
    """The app under test and what the cases are aimed at: a seeded map with references,
    and an empty map for generated adds (so the seeded map stays as it is)."""

    client: TestClient
    session: ASGIClient
    map_id: str
    image_id: str
    adds_map_id: str
    spare: SyntheticView
    # an open capture session of the map that takes adds, for its frames' uploads
    session_id: str


@pytest.fixture(
    scope="module", params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)]
)
def target(
    request: pytest.FixtureRequest,
    tmp_path_factory: pytest.TempPathFactory,
    localizer: Localizer,
    reference_views: list[SyntheticView],
) -> Iterator[Target]:
    database: AbstractContextManager[str]
    if request.param == "sqlite":
        database = nullcontext(f"sqlite:///{tmp_path_factory.mktemp('fuzz') / 'slloc.db'}")
    else:
        admin_url = request.getfixturevalue("postgres_admin_url")
        database = contextmanager(fresh_postgres_database)(admin_url)
    with (
        database as url,
        make_client(url, localizer, api_keys=f"{ADMIN_KEY}:admin") as client,
    ):
        map_id = _new_map(client, "seeded")
        image_id = _created(upload_view(client, map_id, reference_views[0], headers=ADMIN))
        _created(upload_view(client, map_id, reference_views[1], headers=ADMIN))
        # requests go through schemathesis' own transport; the TestClient runs the lifespan
        adds_map_id = _new_map(client, "adds")
        session = client.post(f"/v1/maps/{adds_map_id}/sessions", json={}, headers=ADMIN)
        yield Target(
            client,
            ASGIClient(client.app),
            map_id,
            image_id,
            adds_map_id,
            reference_views[2],
            _created(session),
        )


_doomed = itertools.count()


def _created(response: Any) -> str:
    assert response.status_code == 201, response.text
    return str(response.json()["id"])


def _new_map(client: TestClient, name: str) -> str:
    return _created(client.post("/v1/maps", json={"name": name}, headers=ADMIN))


def _aim(case: schemathesis.Case, target: Target) -> None:
    """Point every other case with a path at the seeded map and image (chosen by a hash of
    the generated path, so the run stays deterministic). A delete is aimed only with valid
    input, at a map or an image made for it, so the seeded ones stay."""
    params = case.path_parameters
    if not params or zlib.crc32(repr(sorted(params.items())).encode()) % 2:
        return
    operation = case.operation.definition.raw["operationId"]
    if operation.startswith("delete_"):
        if case.meta is None or not case.meta.generation.mode.is_positive:
            return  # an invalid path parameter made valid would delete
        name = f"doomed-{next(_doomed)}"
        if operation == "delete_map":
            params["map_id"] = _new_map(target.client, name)
            return
        params["image_id"] = _created(
            upload_view(target.client, target.map_id, target.spare, name, headers=ADMIN)
        )
    elif "image_id" in params:
        params["image_id"] = target.image_id
    params["map_id"] = target.map_id


@schema.parametrize()
@settings(FUZZ_SETTINGS, max_examples=MAX_EXAMPLES)
def test_operations(case: schemathesis.Case, target: Target) -> None:
    _aim(case, target)
    case.call_and_validate(base_url=BASE_URL, session=target.session, checks=CHECKS)


def _json_form_values(component: str) -> st.SearchStrategy[Any]:
    """Values valid against the published schema ``component`` of a JSON form field.
    schemathesis fills such a field with any JSON, so the values come from a probe document
    whose one operation takes the schema as its JSON body."""
    probe = {
        "openapi": DOCUMENT["openapi"],
        "info": DOCUMENT["info"],
        "paths": {
            "/probe": {
                "post": {
                    "requestBody": {
                        "required": True,
                        "content": {
                            "application/json": {
                                "schema": {"$ref": f"#/components/schemas/{component}"}
                            }
                        },
                    },
                    "responses": {"200": {"description": "the value"}},
                }
            }
        },
        "components": DOCUMENT["components"],
    }
    operation = schemathesis.openapi.from_dict(probe)["/probe"]["POST"]
    return operation.as_strategy().map(lambda case: case.body)


# operation id → (JSON form field, its schema, the map it goes to, the image sent with it)
FORM_OPERATIONS = {
    "localize": ("params", "LocalizeParamsIn", "map_id", "query"),
    "add_image": ("metadata", "ImageMetadata", "adds_map_id", "reference"),
    "add_capture_frame": ("metadata", "CaptureFrameMetadata", "adds_map_id", "reference"),
}


@pytest.mark.parametrize("operation_id", sorted(FORM_OPERATIONS))
def test_json_form_fields(
    operation_id: str,
    target: Target,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    """The multipart operations with a real image and a schema-valid JSON form field reach
    the engine (localize) or the reference checks (add): never a server error, every answer
    as documented."""
    field, component, map_attribute, kind = FORM_OPERATIONS[operation_id]
    operation = schema.find_operation_by_id(operation_id)
    views = query_views[:4] if kind == "query" else reference_views[3:7]
    images = [encode_png(view.image) for view in views]
    map_id = getattr(target, map_attribute)

    @given(value=_json_form_values(component), image=st.sampled_from(images))
    @settings(FUZZ_SETTINGS, max_examples=MAX_FORM_EXAMPLES)
    def run(value: Any, image: bytes) -> None:
        path = {"map_id": map_id}
        if "{session_id}" in operation.path:
            path["session_id"] = target.session_id
        case = operation.Case(
            path_parameters=path,
            headers=dict(ADMIN),
            body={"image": image, field: json.dumps(value)},
            media_type="multipart/form-data",
        )
        case.call_and_validate(base_url=BASE_URL, session=target.session, checks=CHECKS)

    run()
