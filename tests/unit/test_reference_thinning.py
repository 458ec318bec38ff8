"""Near-duplicate references thinned out of the retrieved set (issue #13)."""

from __future__ import annotations

import numpy as np
import pytest

from services.retrieval.thinning import thin_references


def _ranked(count: int) -> tuple[np.ndarray, np.ndarray]:
    return np.arange(count, dtype=np.int64), np.linspace(1.0, 0.5, count).astype(np.float32)


def test_a_cluster_of_near_copies_keeps_every_other_frame_and_the_best_first() -> None:
    # a capture along x, 3 cm between frames, ranked best first from the query's end
    centers = np.stack([np.arange(30) * 0.03, np.zeros(30), np.zeros(30)], axis=1)
    rows, scores = _ranked(30)
    kept, kept_scores = thin_references(rows, scores, centers, k=10)
    np.testing.assert_array_equal(kept, np.arange(0, 20, 2))
    np.testing.assert_array_equal(kept_scores, scores[kept])


@pytest.mark.parametrize("unit", [0.001, 1.0, 1000.0])
def test_needs_no_unit(unit: float) -> None:
    rng = np.random.default_rng(1)
    centers = rng.normal(size=(40, 3))
    rows, scores = _ranked(40)
    reference, _ = thin_references(rows, scores, centers, k=10)
    scaled, _ = thin_references(rows, scores, centers * unit, k=10)
    np.testing.assert_array_equal(reference, scaled)


def test_a_second_place_ranked_later_gets_the_slots_the_copies_gave_up() -> None:
    # 12 frames of one place ranked first, then 18 of another 2 m away, 3 cm between frames
    steps = np.concatenate([np.arange(12) * 0.03, 2.0 + np.arange(18) * 0.03])
    centers = np.stack([steps, np.zeros(30), np.zeros(30)], axis=1)
    rows, scores = _ranked(30)
    kept, _ = thin_references(rows, scores, centers, k=10)
    np.testing.assert_array_equal(kept, [0, 2, 4, 6, 8, 10, 12, 14, 16, 18])  # alone: 0…9


def test_too_few_spaced_ones_are_filled_up_in_rank_order() -> None:
    centers = np.zeros((12, 3))  # every candidate at one place
    rows, scores = _ranked(12)
    kept, _ = thin_references(rows, scores, centers, k=10)
    np.testing.assert_array_equal(kept, np.arange(10))


def test_no_more_candidates_than_asked_for_are_returned_as_they_are() -> None:
    rng = np.random.default_rng(2)
    rows = np.array([4, 2, 7], np.int64)
    scores = np.array([0.9, 0.8, 0.7], np.float32)
    kept, kept_scores = thin_references(rows, scores, rng.normal(size=(8, 3)), k=5)
    np.testing.assert_array_equal(kept, rows)
    np.testing.assert_array_equal(kept_scores, scores)
