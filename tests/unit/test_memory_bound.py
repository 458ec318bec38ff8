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
    DEPTH_DECODE_BYTES_PER_PIXEL,
    DEPTH_HELD_BYTES_PER_PIXEL,
    EVALUATION_DESCRIBED,
    EXTRACTION_MIB_PER_MEGAPIXEL,
    FEATURE_BYTES_PER_KEYPOINT,
    IMAGE_DECODE_BYTES_PER_PIXEL,
    IMAGE_HELD_BYTES_PER_PIXEL,
    LIGHTGLUE_MIB_PER_MILLION_PAIRS,
    MATCHER_MIB,
    MIB,
    MODEL_RESIDENT_PER_FILE_MIB,
    REFERENCE_COPIES,
    RUNTIME_MIB,
    SECOND_OPINION_DESCRIBED,
    MemoryBound,
    RequestShape,
    request_memory_mib,
)

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


def _bound(settings: Settings) -> MemoryBound:
    return service_memory_bound(settings, engine_config(settings, plan=thread_plan(settings)))


def _model_file_bytes(settings: Settings) -> int:
    return engine_config(settings).model_file_bytes()


SIFT_FEATURE_BYTES = FEATURE_BYTES_PER_KEYPOINT + 4 * 128  # 524: xy, score, 128 floats


def _largest_request(extraction_rate: float, lightglue: int, feature_bytes: int) -> float:
    """The largest request of ``_settings()``'s limits, by hand: a 40 Mpx upload with its
    depth, extracted at 1024², matched against 50 references of 4096 keypoints; its stages
    peak one after the other, the extraction and the matching beside the pixels held."""
    decode = 40_000_000 * (IMAGE_DECODE_BYTES_PER_PIXEL + DEPTH_DECODE_BYTES_PER_PIXEL) / MIB
    held = 40_000_000 * (IMAGE_HELD_BYTES_PER_PIXEL + DEPTH_HELD_BYTES_PER_PIXEL) / MIB
    extraction = extraction_rate * 1024 * 1024 / 1e6
    matching = (
        MATCHER_MIB
        + LIGHTGLUE_MIB_PER_MILLION_PAIRS * lightglue**2 / 1e6
        + REFERENCE_COPIES * 50 * 4096 * feature_bytes / MIB
    )
    return max(decode, held + extraction, held + matching)


def test_terms_follow_the_settings_arithmetic() -> None:
    bound = _bound(_settings())
    expected = {
        "runtime": RUNTIME_MIB,
        "models": 0.0,  # sift loads no model
        "reference_cache": 256.0,
        "reference_images": 0.0,  # sift's matches are not refined on the images
        # one largest request, whatever the workers: the others wait for its memory
        "computing": _largest_request(EXTRACTION_MIB_PER_MEGAPIXEL["sift"], 0, SIFT_FEATURE_BYTES),
        "bodies": 256.0,
        # a self-evaluation's described references (its queries compute as requests do)
        "self_evaluation": EVALUATION_DESCRIBED * 4096 * SIFT_FEATURE_BYTES / MIB,
        # the references described for second opinions
        "second_opinion": SECOND_OPINION_DESCRIBED * 4096 * SIFT_FEATURE_BYTES / MIB,
        # a vocabulary's training: its sample of 100 000 descriptors, three times, is more
        # than 25 references of 4096 keypoints read at once
        "vocabulary": 3 * 100_000 * SIFT_FEATURE_BYTES / MIB,
    }
    assert bound.terms == pytest.approx(expected, abs=0.06)
    assert bound.fixed_mib == pytest.approx(sum(expected.values()), abs=0.5)


@pytest.mark.parametrize(
    ("features", "rate", "lightglue", "dims"),
    [
        ("aliked", "aliked-n16", 512, 128),
        ("xfeat-lg", "xfeat", 512, 64),
        ("disk", "disk", 4096, 128),
    ],
)
def test_computing_is_the_served_configurations_largest_request(
    features: str, rate: str, lightglue: int, dims: int
) -> None:
    """Each extractor's own rate, its LightGlue's keypoints (disk's sees every keypoint a map
    may ask for, aliked's and xfeat-lg's their best 512) and its descriptors."""
    bound = _bound(_settings(features=features))
    expected = _largest_request(
        EXTRACTION_MIB_PER_MEGAPIXEL[rate], lightglue, FEATURE_BYTES_PER_KEYPOINT + 4 * dims
    )
    assert bound.terms["computing"] == pytest.approx(expected, abs=0.06)


def test_a_request_counts_its_own_shape() -> None:
    """A 640 × 480 query without depth against 20 references of 2048 sift keypoints is a
    fraction of the largest request, and peaks while it matches; a description alone peaks
    while it extracts; the extractor's family is read from its name."""
    query = RequestShape(
        pixels=640 * 480,
        depth=False,
        extracted_pixels=640 * 480,
        extractor="sift-rootsift-2048-1024-c0.02",
        keypoints=2048,
        references=20,
    )
    mib = request_memory_mib(query)
    held = 640 * 480 * IMAGE_HELD_BYTES_PER_PIXEL / MIB
    extraction = EXTRACTION_MIB_PER_MEGAPIXEL["sift"] * 640 * 480 / 1e6
    references = REFERENCE_COPIES * 20 * 2048 * SIFT_FEATURE_BYTES / MIB
    assert mib == pytest.approx(held + MATCHER_MIB + references, abs=0.01)
    assert held + extraction < mib < 100
    described = request_memory_mib(RequestShape(**{**query.__dict__, "references": 0}))
    assert described == pytest.approx(held + extraction, abs=0.01)
    with_depth = request_memory_mib(RequestShape(**{**query.__dict__, "depth": True}))
    assert with_depth - mib == pytest.approx(640 * 480 * DEPTH_HELD_BYTES_PER_PIXEL / MIB)
    unknown = request_memory_mib(RequestShape(**{**query.__dict__, "extractor": "new-net"}))
    assert unknown > mib  # counted at the largest rate known


@pytest.mark.parametrize(
    ("change", "term"),
    [
        ({"max_side": 2048}, "computing"),
        ({"max_image_pixels": 10_000_000}, "computing"),
        ({"max_top_k": 10}, "computing"),
        ({"max_keypoints": 1024}, "computing"),
        ({"computing_memory_mib": 4000}, "computing"),
        ({"body_memory_mib": 512}, "bodies"),
        ({"reference_cache_mib": 0}, "reference_cache"),
        ({"evaluation_features": "aliked"}, "computing"),
    ],
)
def test_each_setting_moves_its_term(change: dict[str, object], term: str) -> None:
    before = _bound(_settings())
    after = _bound(_settings(**change))
    assert after.terms[term] != before.terms[term]
    assert after.fixed_mib != before.fixed_mib


def test_computing_holds_at_least_one_largest_request() -> None:
    """A budget below the largest request counts as the largest request; the workers do not
    multiply it."""
    largest = _bound(_settings()).terms["computing"]
    assert _bound(_settings(computing_memory_mib=100)).terms["computing"] == largest
    assert _bound(_settings(localize_workers=1, cpu_cores=1)).terms["computing"] == largest
    assert _bound(_settings(computing_memory_mib=5000)).terms["computing"] == 5000


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
    models add up, and the largest request is the most demanding one's (an xfeat-lg server
    that serves sift too extracts like sift at 1024 px and matches its 128-float
    descriptors)."""
    xfeat = _settings(features="xfeat-lg")
    both = _settings(features="xfeat-lg", evaluation_features="sift")
    alone, served = _bound(xfeat).terms, _bound(both).terms
    assert served["models"] == alone["models"]  # sift loads no model
    sift = _bound(_settings()).terms
    assert served["computing"] == pytest.approx(sift["computing"], abs=0.1)
    assert served["self_evaluation"] == pytest.approx(sift["self_evaluation"], abs=0.1)
    assert served["computing"] > alone["computing"]
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
