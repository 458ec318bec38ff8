"""The committed OpenAPI document matches the app; regenerate with `slloc openapi`."""

from pathlib import Path

from app.openapi import openapi_document

COMMITTED = Path(__file__).resolve().parents[1] / "openapi" / "openapi.json"


def test_openapi_is_up_to_date() -> None:
    assert COMMITTED.read_text() == openapi_document(), (
        "openapi/openapi.json is stale: run `slloc openapi` and commit the result"
    )


def test_every_error_is_documented_as_problem_json() -> None:
    import json

    doc = json.loads(COMMITTED.read_text())
    for path, operations in doc["paths"].items():
        for method, operation in operations.items():
            for status, response in operation["responses"].items():
                if status.startswith(("4", "5")):
                    assert "application/problem+json" in response["content"], (method, path, status)
