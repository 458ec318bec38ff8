"""Near-duplicate references thinned out of the retrieved set; references on a track looked
along, and close ones looking elsewhere, kept."""

from __future__ import annotations

import numpy as np
import pytest

from services.retrieval.cache import RetrievalIndexCache
from services.retrieval.contracts import RetrievalIndex
from services.retrieval.thinning import (
    NEAR_COPY_TURN_DEG,
    SPACING_FACTOR,
    on_track,
    search_thinned,
    thin_references,
)


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


def _index(centers: np.ndarray, axes: np.ndarray | None) -> RetrievalIndex:
    """References ranked by their row for the query ``QUERY``: row i at angle 0.01·i."""
    angles = 0.01 * np.arange(len(centers))
    descriptors = np.zeros((len(centers), 4), np.float32)
    descriptors[:, 0], descriptors[:, 1] = np.cos(angles), np.sin(angles)
    ids = [f"r{i}" for i in range(len(centers))]
    return RetrievalIndex(ids, descriptors, centers, axes=axes)


QUERY = np.array([1.0, 0.0, 0.0, 0.0], np.float32)


def _line(count: int, spacing: float, along: int) -> np.ndarray:
    centers = np.zeros((count, 3))
    centers[:, along] = np.arange(count) * spacing
    return centers


def test_a_track_looked_along_keeps_every_reference_near_the_first() -> None:
    # a vehicle's frames 2.3 m apart along z, looking along z
    centers = _line(30, 2.3, along=2)
    forward = np.tile([0.0, 0.0, 1.0], (30, 1))
    assert on_track(centers, forward)
    kept, _ = search_thinned(_index(centers, forward), QUERY, k=10)
    np.testing.assert_array_equal(kept, np.arange(10))


def test_a_line_looked_across_is_thinned_as_near_copies() -> None:
    # frames along x looking along z (a sideways sweep): not a track
    centers = _line(30, 0.03, along=0)
    forward = np.tile([0.0, 0.0, 1.0], (30, 1))
    assert not on_track(centers, forward)
    kept, _ = search_thinned(_index(centers, forward), QUERY, k=10)
    np.testing.assert_array_equal(kept, np.arange(0, 20, 2))


def _turning(count: int, degrees_per_frame: float) -> np.ndarray:
    """Optical axes turning about y from z by ``degrees_per_frame`` a frame."""
    angles = np.radians(degrees_per_frame) * np.arange(count)
    return np.stack([np.sin(angles), np.zeros(count), np.cos(angles)], axis=1)


@pytest.mark.parametrize(
    ("turn", "expected"),
    [(2 * NEAR_COPY_TURN_DEG, np.arange(10)), (NEAR_COPY_TURN_DEG / 2, np.arange(0, 20, 2))],
)
def test_close_frames_that_look_elsewhere_are_no_near_copies(
    turn: float, expected: np.ndarray
) -> None:
    # a sideways sweep, 3 cm between frames, the camera turning as it goes
    centers = _line(30, 0.03, along=0)
    axes = _turning(30, turn)
    assert not on_track(centers, axes)
    kept, _ = search_thinned(_index(centers, axes), QUERY, k=10)
    np.testing.assert_array_equal(kept, expected)
    # the wider retrieval spreads by position alone
    kept, _ = search_thinned(_index(centers, axes), QUERY, k=10, spacing_factor=SPACING_FACTOR)
    np.testing.assert_array_equal(kept, np.arange(0, 20, 2))


def test_without_axes_or_with_a_factor_given_the_track_rule_does_not_apply() -> None:
    centers = _line(30, 2.3, along=2)
    forward = np.tile([0.0, 0.0, 1.0], (30, 1))
    every_other = np.arange(0, 20, 2)
    kept, _ = search_thinned(_index(centers, None), QUERY, k=10)
    np.testing.assert_array_equal(kept, every_other)
    kept, _ = search_thinned(_index(centers, forward), QUERY, k=10, spacing_factor=SPACING_FACTOR)
    np.testing.assert_array_equal(kept, every_other)


def test_the_retrieval_cache_keeps_each_references_axis_through_adds_and_deletes() -> None:
    source = _AxesSource(["a", "b", "c"])
    cache = RetrievalIndexCache()
    index = cache.index(source)
    assert index.axes is not None
    np.testing.assert_array_equal(index.axes[:, 0], [0, 1, 2])
    source.ids, source.rev = ["a", "c", "d"], 2
    index = cache.index(source)
    assert index.image_ids == ["a", "c", "d"] and index.axes is not None
    np.testing.assert_array_equal(index.axes[:, 0], [0, 2, 3])


class _AxesSource:
    """A map whose reference ``x`` has the axis (ord(x) - ord("a"), 0, 0)."""

    map_id, feature_model, descriptor_model = "map", "features", "descriptors"

    def __init__(self, ids: list[str]) -> None:
        self.ids, self.rev = ids, 1

    def revision(self) -> int:
        return self.rev

    def reference_ids(self) -> list[str]:
        return list(self.ids)

    def vocabulary(self) -> None:
        return None

    def load_index(self, vocabulary: object, only_ids: list[str] | None = None) -> RetrievalIndex:
        ids = sorted(self.ids if only_ids is None else only_ids)
        axes = np.array([[ord(i) - ord("a"), 0.0, 0.0] for i in ids])
        return RetrievalIndex(
            ids, np.ones((len(ids), 4), np.float32), np.zeros((len(ids), 3)), axes=axes
        )
