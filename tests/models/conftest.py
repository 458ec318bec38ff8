"""The exported ONNX models (``scripts/build_models.sh`` writes them; CI always builds them).

``SLLOC_TEST_MODELS_DIR`` points elsewhere than ``./models``. Without models these tests skip,
except under CI, where a missing model is a failure. ``models`` needs ALIKED + LightGlue,
``disk_models`` DISK + LightGlue-DISK, ``xfeat_models`` XFeat + LighterGlue.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from services.components import ModelStore
from services.features.configs import FEATURE_CONFIGS
from services.runtime.manifest import read_manifest

MODELS_DIR = Path(os.environ.get("SLLOC_TEST_MODELS_DIR", "models"))
ALIKED_MODELS = FEATURE_CONFIGS["aliked"].models
DISK_MODELS = ("disk", "lightglue-disk")
XFEAT_MODELS = ("xfeat", "lighterglue-xfeat")


def _store(names: tuple[str, ...]) -> ModelStore:
    entries = read_manifest(MODELS_DIR)
    missing = [name for name in names if name not in entries]
    if missing:
        message = f"models {missing} are not built in {MODELS_DIR} (scripts/build_models.sh)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return ModelStore(MODELS_DIR)


@pytest.fixture(scope="session")
def models() -> ModelStore:
    return _store(ALIKED_MODELS)


@pytest.fixture(scope="session")
def disk_models() -> ModelStore:
    return _store(DISK_MODELS)


@pytest.fixture(scope="session")
def xfeat_models() -> ModelStore:
    return _store(XFEAT_MODELS)
