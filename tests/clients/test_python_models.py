"""The Python SDK's models (clients/python/src/slloc_client/models.py) are those its generator
writes from openapi/openapi.json today, one model per object schema with the same fields."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

from pydantic import BaseModel
from slloc_client import models

ROOT = Path(__file__).resolve().parents[2]
DOCUMENT = ROOT / "openapi" / "openapi.json"


def _generator() -> ModuleType:
    path = ROOT / "clients" / "python" / "generate_models.py"
    spec = importlib.util.spec_from_file_location("slloc_client_generator", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_committed_models_are_generated_from_the_document() -> None:
    committed = (ROOT / "clients" / "python" / "src" / "slloc_client" / "models.py").read_text()
    assert _generator().generated(DOCUMENT) == committed, (
        "clients/python models are stale: run .venv/bin/python clients/python/generate_models.py"
    )


def test_every_object_schema_has_a_model_with_its_fields() -> None:
    schemas = json.loads(DOCUMENT.read_text())["components"]["schemas"]
    class_name = _generator()._class_name
    objects = {name: s for name, s in schemas.items() if "properties" in s}
    assert {"MapOut", "ImageOut", "LocalizeResult", "Problem", "HealthOut"} <= set(objects)
    for name, schema in objects.items():
        model = getattr(models, class_name(name))
        assert issubclass(model, BaseModel)
        fields = {field.alias or key for key, field in model.model_fields.items()}
        assert fields == set(schema["properties"]), name
        required = {
            field.alias or key for key, field in model.model_fields.items() if field.is_required()
        }
        assert required == set(schema.get("required", [])), name
