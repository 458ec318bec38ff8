"""The memory bound from the settings (``services/runtime/memory.py``): each term's
arithmetic, and each setting moving its term."""

from __future__ import annotations

from pathlib import Path

import pytest

from app.engine_config import engine_config, service_memory_bound, thread_plan
from app.settings import Settings
from services.features.configs import get_feature_config
from services.runtime.manifest import read_manifest
from services.runtime.memory import (
    DECODE_BYTES_PER_PIXEL,
    EXTRACTION_MIB_PER_MEGAPIXEL,
    FEATURE_BYTES_PER_KEYPOINT,
    MATCHER_MIB,
    MIB,
    MODEL_RESIDENT_PER_FILE_MIB,
    RUNTIME_MIB,
    MemoryBound,
)
from services.runtime.threads import ThreadPlan, plan_threads

MODELS = Path(__file__).resolve().parents[2] / "models"


def _settings(**values: object) -> Settings:
    base: dict[str, object] = {
        "database_url": "sqlite://",
        "models_dir": MODELS,
        "features": "sift",
        "cpu_cores": 2,
        "localize_workers": 2,
        "max_queued": 8,
        "max_upload_bytes": 25 * MIB,
        "max_image_pixels": 40_000_000,
        "max_side": 1024,
        "max_keypoints": 4096,
        "max_top_k": 50,
        "reference_cache_mib": 256,
        "limit_concurrency": 64,
    }
    return Settings(**{**base, **values})  # type: ignore[arg-type]


def _bound(settings: Settings, plan: ThreadPlan | None = None) -> MemoryBound:
    plan = plan or thread_plan(settings)
    return service_memory_bound(settings, engine_config(settings, plan=plan), plan)


def _model_file_bytes(settings: Settings) -> int:
    return engine_config(settings).model_file_bytes()


def test_terms_follow_the_settings_arithmetic() -> None:
    settings = _settings()
    bound = _bound(settings)
    workers = 2
    expected = {
        "runtime": RUNTIME_MIB,
        "models": 0.0,  # sift loads no model
        "reference_cache": 256.0,
        "extraction": workers * EXTRACTION_MIB_PER_MEGAPIXEL * 1024 * 1024 / 1e6,
        "decode": workers * DECODE_BYTES_PER_PIXEL * 40_000_000 / MIB,
        "matching": workers * (MATCHER_MIB + 50 * 4096 * FEATURE_BYTES_PER_KEYPOINT / MIB),
        "uploads": (workers + 8) * 2 * 25.0,
        "bodies": 64 * (2 * 25.0 + 1),
    }
    assert bound.terms == pytest.approx(expected, abs=0.06)
    assert bound.fixed_mib == pytest.approx(sum(expected.values()), abs=0.5)
    # the extraction at the default 1024 px cap: about 3 GiB a worker (measured 3092 MiB)
    assert 3000 < bound.terms["extraction"] / workers < 3200


@pytest.mark.parametrize(
    ("change", "term"),
    [
        ({"max_side": 2048}, "extraction"),
        ({"localize_workers": 1}, "extraction"),
        ({"max_image_pixels": 10_000_000}, "decode"),
        ({"max_top_k": 10}, "matching"),
        ({"max_keypoints": 1024}, "matching"),
        ({"max_queued": 0}, "uploads"),
        ({"max_upload_bytes": 5 * MIB}, "uploads"),
        ({"max_upload_bytes": 5 * MIB}, "bodies"),
        ({"limit_concurrency": 16}, "bodies"),
        ({"reference_cache_mib": 0}, "reference_cache"),
    ],
)
def test_each_setting_moves_its_term(change: dict[str, object], term: str) -> None:
    before = _bound(_settings())
    after = _bound(_settings(**change))
    assert after.terms[term] != before.terms[term]
    assert after.fixed_mib != before.fixed_mib


def test_workers_come_from_the_thread_plan() -> None:
    settings = _settings(localize_workers=0, cpu_cores=1)
    assert plan_threads(1).workers == 1
    one = _bound(settings)
    two = _bound(settings, plan_threads(2))
    assert two.terms["extraction"] == pytest.approx(2 * one.terms["extraction"], abs=0.1)
    assert two.terms["uploads"] - one.terms["uploads"] == pytest.approx(50.0)


def test_models_term_is_the_configurations_files() -> None:
    entries = read_manifest(MODELS)
    config = get_feature_config("aliked")
    if not all(m in entries for m in config.models):
        pytest.skip("aliked's models are not built (scripts/build_models.sh)")
    size = sum((MODELS / entries[m].file).stat().st_size for m in config.models)
    settings = _settings(features="aliked", localize_workers=1)
    assert _model_file_bytes(settings) == size
    mib = _bound(settings).terms["models"]
    assert mib == pytest.approx(MODEL_RESIDENT_PER_FILE_MIB * size / MIB, abs=0.06)
    assert 100 < mib < 200  # measured: 137 MiB resident for aliked + lightglue
    # two workers: the extractor has a second session, on both workers' threads
    extractor = (MODELS / entries[config.extractor].file).stat().st_size
    assert _model_file_bytes(_settings(features="aliked")) == size + extractor


def test_retrieval_index_adds_to_the_total() -> None:
    bound = MemoryBound({"runtime": 10.0, "models": 5.0})
    grown = bound.with_retrieval_index(3 * MIB)
    assert (bound.total_mib, grown.total_mib, grown.fixed_mib) == (15.0, 18.0, 15.0)
    assert "retrieval_index 3" in grown.describe()
