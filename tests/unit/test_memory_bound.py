"""The memory bound from the settings (``services/runtime/memory.py``): each term's
arithmetic, and each setting moving its term."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from app.engine_config import engine_config, service_memory_bound, thread_plan
from app.settings import Settings
from services.features.configs import get_feature_config
from services.runtime.manifest import read_manifest
from services.runtime.memory import (
    DECODE_BYTES_PER_PIXEL,
    EVALUATION_DESCRIBED,
    EXTRACTION_MIB_PER_MEGAPIXEL,
    FEATURE_BYTES_PER_KEYPOINT,
    LIGHTGLUE_MIB_PER_MILLION_PAIRS,
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
        "max_upload_bytes": 25 * MIB,
        "body_memory_mib": 256,
        "max_image_pixels": 40_000_000,
        "max_side": 1024,
        "max_keypoints": 4096,
        "max_top_k": 50,
        "reference_cache_mib": 256,
        "evaluation_features": "",
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
    sift_feature_bytes = 2 * (FEATURE_BYTES_PER_KEYPOINT + 4 * 128)  # 1048: xy, 128 floats, score
    expected = {
        "runtime": RUNTIME_MIB,
        "models": 0.0,  # sift loads no model
        "reference_cache": 256.0,
        "reference_images": 0.0,  # sift's matches are not refined on the images
        "extraction": workers * EXTRACTION_MIB_PER_MEGAPIXEL["sift"] * 1024 * 1024 / 1e6,
        "decode": workers * DECODE_BYTES_PER_PIXEL * 40_000_000 / MIB,
        "matching": workers * (MATCHER_MIB + 50 * 4096 * sift_feature_bytes / MIB),
        "bodies": 256.0,
        # a self-evaluation's described references (it computes in a worker's place)
        "self_evaluation": EVALUATION_DESCRIBED * 4096 * sift_feature_bytes / 2 / MIB,
    }
    assert bound.terms == pytest.approx(expected, abs=0.06)
    assert bound.fixed_mib == pytest.approx(sum(expected.values()), abs=0.5)
    # sift's extraction at the default 1024 px cap: about 240 MiB a worker (measured 232 MiB)
    assert 220 < bound.terms["extraction"] / workers < 260


@pytest.mark.parametrize(
    ("features", "low", "high"),
    [("aliked", 3000, 3200), ("xfeat-lg", 120, 150), ("disk", 2700, 2900)],
)
def test_extraction_is_the_served_extractors(features: str, low: float, high: float) -> None:
    """Each extractor's own rate (measured at 1024²: aliked 3092, xfeat 123, disk 2153 MiB,
    the largest rate of its sizes counted)."""
    bound = _bound(_settings(features=features, localize_workers=1))
    assert low < bound.terms["extraction"] < high


def test_matching_grows_with_the_keypoints_lightglue_sees() -> None:
    """disk's LightGlue sees every keypoint a map may ask for, xfeat-lg's its best 512 and
    64-float descriptors."""
    disk = _bound(_settings(features="disk", localize_workers=1)).terms["matching"]
    xfeat = _bound(_settings(features="xfeat-lg", localize_workers=1)).terms["matching"]
    lightglue_disk = LIGHTGLUE_MIB_PER_MILLION_PAIRS * 4096**2 / 1e6
    features_128 = 50 * 4096 * 2 * (FEATURE_BYTES_PER_KEYPOINT + 4 * 128) / MIB
    assert disk == pytest.approx(MATCHER_MIB + lightglue_disk + features_128, abs=0.06)
    features_64 = 50 * 4096 * 2 * (FEATURE_BYTES_PER_KEYPOINT + 4 * 64) / MIB
    lightglue_xfeat = LIGHTGLUE_MIB_PER_MILLION_PAIRS * 512**2 / 1e6
    assert xfeat == pytest.approx(MATCHER_MIB + lightglue_xfeat + features_64, abs=0.06)


@pytest.mark.parametrize(
    ("change", "term"),
    [
        ({"max_side": 2048}, "extraction"),
        ({"localize_workers": 1}, "extraction"),
        ({"max_image_pixels": 10_000_000}, "decode"),
        ({"max_top_k": 10}, "matching"),
        ({"max_keypoints": 1024}, "matching"),
        ({"body_memory_mib": 512}, "bodies"),
        ({"reference_cache_mib": 0}, "reference_cache"),
        ({"evaluation_features": "aliked"}, "extraction"),
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
    assert two.terms["decode"] == pytest.approx(2 * one.terms["decode"], abs=0.2)


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


def test_body_memory_holds_at_least_the_largest_body() -> None:
    with pytest.raises(ValueError, match="body_memory_mib 64 is below"):
        _settings(body_memory_mib=64)  # 1.7 × 51 MiB = 87 MiB
    assert _settings(body_memory_mib=64, max_upload_bytes=10 * MIB).body_memory_mib == 64


def test_retrieval_index_adds_to_the_total() -> None:
    bound = MemoryBound({"runtime": 10.0, "models": 5.0})
    grown = bound.with_retrieval_index(3 * MIB)
    assert (bound.total_mib, grown.total_mib, grown.fixed_mib) == (15.0, 18.0, 15.0)
    assert "retrieval_index 3" in grown.describe()


def test_every_configuration_served_is_counted() -> None:
    """Maps may be served with the configurations of SLLOC_EVALUATION_FEATURES as well: their
    models add up, and a worker's extraction and matching are the most demanding one's (an
    xfeat-lg server that serves sift too extracts like sift at 1024 px and matches its
    128-float descriptors)."""
    xfeat = _settings(features="xfeat-lg")
    both = _settings(features="xfeat-lg", evaluation_features="sift")
    alone, served = _bound(xfeat).terms, _bound(both).terms
    assert served["models"] == alone["models"]  # sift loads no model
    sift = _bound(_settings()).terms
    assert served["extraction"] == pytest.approx(sift["extraction"], abs=0.1)
    assert served["self_evaluation"] == pytest.approx(sift["self_evaluation"], abs=0.1)
    assert served["matching"] > alone["matching"]
    settings = _settings(features="xfeat-lg", evaluation_features="aliked")
    aliked = replace(
        engine_config(settings), features="aliked", wide_threads=None
    ).model_file_bytes()
    expected = alone["models"] + MODEL_RESIDENT_PER_FILE_MIB * aliked / MIB
    assert _bound(settings).terms["models"] == pytest.approx(expected, abs=0.1)


def test_reference_images_count_where_a_configuration_refines_its_matches() -> None:
    assert _bound(_settings()).terms["reference_images"] == 0  # sift alone
    refining = _settings(evaluation_features="xfeat-lg", reference_image_cache_mib=32)
    assert _bound(refining).terms["reference_images"] == 32
