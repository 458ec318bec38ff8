"""A client generated from ``openapi/openapi.json`` by openapi-python-client works unmodified:
multipart file fields are ``format: binary`` (typed as files, not strings), and the generated
package creates a map, uploads reference images and localizes a query against a live server.
The generation test is skipped when the generator is not installed (``pip install '.[dev]'``).
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import uvicorn

from app.main import create_app
from app.settings import Settings
from services.localization.localizer import Localizer
from tests.conftest import image_metadata
from tools.synthetic.scene import SyntheticView, encode_png

DOCUMENT = Path(__file__).resolve().parents[2] / "openapi" / "openapi.json"
PACKAGE = "slloc_generated"


def _file_fields(node: Any) -> Iterator[dict[str, Any]]:
    if isinstance(node, dict):
        if node.get("contentMediaType") == "application/octet-stream":
            yield node
        for value in node.values():
            yield from _file_fields(value)
    elif isinstance(node, list):
        for value in node:
            yield from _file_fields(value)


def test_multipart_file_fields_are_binary_and_json_fields_documented() -> None:
    document = json.loads(DOCUMENT.read_text())
    bodies = {
        name: schema
        for name, schema in document["components"]["schemas"].items()
        if name.startswith("Body_")
    }
    assert {"Body_add_image", "Body_localize"} <= set(bodies)
    fields = [field for body in bodies.values() for field in _file_fields(body)]
    assert len(fields) >= 4  # image and depth of both routes
    assert all(field["type"] == "string" and field["format"] == "binary" for field in fields)
    for body, name, model in (
        ("Body_add_image", "metadata", "ImageMetadata"),
        ("Body_localize", "params", "LocalizeParamsIn"),
    ):
        field = bodies[body]["properties"][name]
        assert field["type"] == "string" and field["contentMediaType"] == "application/json"
        assert field["contentSchema"] == {"$ref": f"#/components/schemas/{model}"}
        assert model in field["description"] and model in document["components"]["schemas"]


@pytest.fixture
def live_url(tmp_path: Path, localizer: Localizer) -> Iterator[str]:
    """The service over HTTP (uvicorn in a thread) on a fresh SQLite database."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    app = create_app(
        Settings(database_url=f"sqlite:///{tmp_path / 'slloc.db'}"), localizer=localizer
    )
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.05)
    yield f"http://127.0.0.1:{port}"
    server.should_exit = True
    thread.join(timeout=30)


@pytest.fixture
def generated(tmp_path: Path) -> Iterator[Any]:
    """The package openapi-python-client generates from the committed document, imported."""
    if importlib.util.find_spec("openapi_python_client") is None:
        pytest.skip("openapi-python-client is not installed (pip install '.[dev]')")
    config = tmp_path / "generator.yaml"
    config.write_text(f"post_hooks: []\npackage_name_override: {PACKAGE}\n")
    out = tmp_path / "generated"
    out.mkdir()
    subprocess.run(
        [
            *(sys.executable, "-m", "openapi_python_client", "generate"),
            *("--path", str(DOCUMENT), "--meta", "none", "--config", str(config)),
            *("--output-path", str(out / PACKAGE)),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    sys.path.insert(0, str(out))
    try:
        yield importlib.import_module(PACKAGE)
    finally:
        sys.path.remove(str(out))
        for name in [n for n in sys.modules if n == PACKAGE or n.startswith(f"{PACKAGE}.")]:
            del sys.modules[name]


def test_generated_client_uploads_and_localizes(
    generated: Any,
    live_url: str,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    api = importlib.import_module(f"{PACKAGE}.api")
    create_map = importlib.import_module(f"{PACKAGE}.api.maps.create_map")
    add_image = importlib.import_module(f"{PACKAGE}.api.images.add_image")
    localize = importlib.import_module(f"{PACKAGE}.api.localize.localize")
    models = importlib.import_module(f"{PACKAGE}.models")
    types = importlib.import_module(f"{PACKAGE}.types")
    assert api is not None
    client = generated.AuthenticatedClient(base_url=live_url, token="unused", timeout=120.0)

    made = create_map.sync_detailed(client=client, body=models.MapCreate(name="generated"))
    assert made.status_code == 201, made.content
    map_id = made.parsed.id
    for view in reference_views[:12]:
        body = models.BodyAddImage(
            image=types.File(payload=encode_png(view.image), file_name=view.name),
            metadata=json.dumps(image_metadata(view)),
        )
        added = add_image.sync_detailed(map_id, client=client, body=body)
        assert added.status_code == 201, added.content

    query = query_views[0]
    camera = image_metadata(query)["camera"]
    body = models.BodyLocalize(
        image=[types.File(payload=encode_png(query.image), file_name=query.name)],
        params=json.dumps({"camera": camera}),
    )
    answer = localize.sync_detailed(map_id, client=client, body=body)
    assert answer.status_code == 200, answer.content
    result = json.loads(answer.content)
    assert result["localized"] is True, result
