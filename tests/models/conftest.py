"""The exported ONNX models (``scripts/build_models.sh`` writes them; CI always builds them).

``SLLOC_TEST_MODELS_DIR`` points elsewhere than ``./models``. Without models these tests skip,
except under CI, where a missing model is a failure.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from services.components import PREFERRED_MODELS, ModelStore
from services.runtime.manifest import read_manifest

MODELS_DIR = Path(os.environ.get("SLLOC_TEST_MODELS_DIR", "models"))


@pytest.fixture(scope="session")
def models() -> ModelStore:
    entries = read_manifest(MODELS_DIR)
    missing = [name for name in PREFERRED_MODELS if name not in entries]
    if missing:
        message = f"models {missing} are not built in {MODELS_DIR} (scripts/build_models.sh)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return ModelStore(MODELS_DIR)
