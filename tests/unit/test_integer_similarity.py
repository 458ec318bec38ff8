import numpy as np
import pytest

from services.features.base import LocalFeatures
from services.matching import nearest_neighbor
from services.matching.integer_similarity import IntegerSimilarity, quantize_query
from services.matching.nearest_neighbor import NearestNeighborMatcher
from tools.benchmarks.matching import float_ratios


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def _rootsift_like(rng: np.random.Generator, n: int) -> np.ndarray:
    """Non-negative unit 128-d descriptors whose largest component is about 0.3, as
    RootSIFT's are on kitti05 and redkitchen."""
    return _unit(np.abs(rng.normal(size=(n, 128))))


def _features(descriptors: np.ndarray) -> LocalFeatures:
    n = len(descriptors)
    return LocalFeatures(
        np.zeros((n, 2), np.float32), descriptors, np.ones(n, np.float32), (640, 480)
    )


@pytest.mark.parametrize(("dimensions", "signed"), [(128, False), (64, True)])
def test_cosines_within_a_rounding_step(dimensions: int, signed: bool) -> None:
    rng = np.random.default_rng(dimensions)
    raw = rng.normal(size=(700, dimensions))
    descriptors = _unit(raw if signed else np.abs(raw))
    query, reference = descriptors[:300], descriptors[300:]
    product = IntegerSimilarity(quantize_query(query), reference)
    blocks = [(start, block.copy()) for start, block in product.blocks(128)]
    assert [start for start, _ in blocks] == [0, 128, 256]
    similarity = np.vstack([block for _, block in blocks])
    assert similarity.shape == (300, 400) and similarity.dtype == np.int32
    error = np.abs(similarity * product.cosine - query @ reference.T)
    assert error.max() < 0.02
    assert np.median(error) < 2e-3


def test_zero_descriptors_have_zero_similarity() -> None:
    product = IntegerSimilarity(
        quantize_query(np.zeros((2, 8), np.float32)), np.ones((3, 8), np.float32)
    )
    [(_, similarity)] = product.blocks(1024)
    assert similarity.shape == (2, 3) and not similarity.any()


def test_matches_are_float_matching_but_at_the_ratio_tests_edge() -> None:
    rng = np.random.default_rng(4)
    reference = _rootsift_like(rng, 2000)
    order = rng.permutation(2000)[:1500]
    # correspondences from clear to hopeless, so that ratios spread over the test's edge
    noise = np.linspace(0.01, 0.2, 1500)[:, None] * rng.normal(size=(1500, 128))
    query = _unit(np.abs(reference[order] + noise))
    best, ratio = float_ratios(query, reference)

    matches = NearestNeighborMatcher(0.8).match(_features(query), _features(reference))

    kept = np.zeros(len(query), bool)
    kept[matches[:, 0]] = True
    assert np.array_equal(matches[:, 1], best[matches[:, 0]])
    assert kept[ratio < 0.78].all()
    assert not kept[ratio > 0.82].any()
    assert 300 < kept.sum() < 1200  # the edge is crossed, not avoided
    assert (kept != (ratio < 0.8)).sum() <= 0.02 * kept.sum()


def test_blocks_of_query_rows_match_as_one_product(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(5)
    reference = _rootsift_like(rng, 900)
    noise = np.linspace(0.01, 0.2, 700)[:, None] * rng.normal(size=(700, 128))
    query = _features(_unit(np.abs(reference[rng.permutation(900)[:700]] + noise)))
    whole = NearestNeighborMatcher(0.8).match(query, _features(reference))
    monkeypatch.setattr(nearest_neighbor, "QUERY_BLOCK", 64)  # 11 blocks, the last of 60 rows
    blocked = NearestNeighborMatcher(0.8).match(query, _features(reference))
    assert len(whole) > 100
    assert np.array_equal(blocked, whole)
