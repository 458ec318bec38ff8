"""The OpenAPI document of the app as ``create_app`` builds it (its hook:
``app/api/openapi.py``), as committed in ``openapi/openapi.json`` (``slloc openapi``)."""

from __future__ import annotations

import json

from app.main import create_app
from app.settings import Settings


def openapi_document() -> str:
    app = create_app(Settings(database_url="sqlite://", api_keys=""))
    return json.dumps(app.openapi(), indent=2, sort_keys=True) + "\n"
