"""The app's OpenAPI hook: every error as problem+json, and the schemas of the JSON form fields
in the components (the committed copy is written by ``app/openapi.py``)."""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from pydantic import BaseModel

from app.errors import document_problems
from app.schemas.captures import CaptureFrameMetadata
from app.schemas.images import ImageMetadata
from app.schemas.localize import LocalizeParamsIn

# models sent as JSON strings in multipart form fields (see ``app.api.deps.json_form_schema``)
JSON_FORM_MODELS: tuple[type[BaseModel], ...] = (
    ImageMetadata,
    LocalizeParamsIn,
    CaptureFrameMetadata,
)


def install_openapi(app: FastAPI) -> None:
    """Make ``app.openapi()`` return the completed document."""
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        schema = generate()
        document_problems(schema)
        publish_json_form_models(schema)
        type_binary_uploads(schema)
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


def type_binary_uploads(schema: dict[str, Any]) -> None:
    """Mark every multipart file field (FastAPI writes OpenAPI 3.1's ``contentMediaType:
    application/octet-stream``) ``format: binary`` too, as OpenAPI 3.0 does, so that client
    generators (openapi-python-client, openapi-generator) type it as a file, not a string."""

    def mark(node: Any) -> None:
        if isinstance(node, dict):
            if node.get("type") == "string" and (
                node.get("contentMediaType") == "application/octet-stream"
            ):
                node["format"] = "binary"
            for value in node.values():
                mark(value)
        elif isinstance(node, list):
            for value in node:
                mark(value)

    for name, component in schema.get("components", {}).get("schemas", {}).items():
        if name.startswith("Body_"):  # the request bodies of the multipart routes
            mark(component)


def publish_json_form_models(schema: dict[str, Any]) -> None:
    """Add the schemas of ``JSON_FORM_MODELS`` (and the models they use) to the components."""
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    for model in JSON_FORM_MODELS:
        model_schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
        for name, definition in model_schema.pop("$defs", {}).items():
            components.setdefault(name, definition)
        components[model.__name__] = model_schema
