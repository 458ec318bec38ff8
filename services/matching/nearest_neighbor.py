"""Mutual nearest-neighbour matching with Lowe's ratio test on L2-normalised descriptors,
their similarities computed in 8-bit integers (``services.matching.integer_similarity``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from services.features.base import LocalFeatures
from services.matching.base import match_each
from services.matching.integer_similarity import (
    IntegerSimilarity,
    QuantizedQuery,
    quantize_query,
)
from services.runtime.spare_workers import Spread
from services.types import Float32Array, IntArray

# query keypoints compared at once: a block of 512 against 4096 reference keypoints is 8 MiB
# of similarities, an eighth of a whole 4096 × 4096 pair, and is written into one buffer, so
# a pair of kitti05 frames with 4096 keypoints each takes 13 ms instead of 24 unblocked
# (fresh pages; blocks of 256–1024 as fast; python -m tools.benchmarks.matching)
QUERY_BLOCK = 512


class NearestNeighborMatcher:
    """Keeps a pair when each keypoint is the other's nearest neighbour and the nearest
    distance is below ``ratio`` × the second-nearest (in the query → reference direction),
    and, with ``min_similarity``, their cosine similarity is above it (XFeat's own matcher
    keeps mutual neighbours above 0.82).

    Default 0.8 (was 0.85): on redkitchen it keeps recall (slightly higher) while halving the
    matches of unrelated images, so their spurious epipolar consensus shrinks as well."""

    def __init__(self, ratio: float = 0.8, min_similarity: float | None = None) -> None:
        if not 0.0 < ratio <= 1.0:
            raise ValueError(f"ratio must be in (0, 1], got {ratio}")
        if min_similarity is not None and not -1.0 <= min_similarity < 1.0:
            raise ValueError(f"min_similarity must be in [-1, 1), got {min_similarity}")
        self.ratio = ratio
        self.min_similarity = min_similarity
        floor = "" if min_similarity is None else f"-cos-{min_similarity:g}"
        self.name = f"mnn-ratio-{ratio:g}{floor}"

    def match(self, query: LocalFeatures, reference: LocalFeatures) -> IntArray:
        return self._match(quantize_query(query.descriptors), reference.descriptors)

    def _match(self, query: QuantizedQuery, reference: Float32Array) -> IntArray:
        if len(query.values) < 2 or len(reference) < 2:
            return np.zeros((0, 2), dtype=np.int64)
        similarity = IntegerSimilarity(query, reference)
        n = len(query.values)
        best = np.empty(n, np.int64)
        first = np.empty(n, np.int32)
        second = np.empty(n, np.int32)
        column_max = np.full(len(reference), np.iinfo(np.int32).min, np.int32)
        for start, block in similarity.blocks(QUERY_BLOCK):
            rows = np.arange(len(block))
            end = start + len(block)
            best[start:end] = np.argmax(block, axis=1)
            first[start:end] = block[rows, best[start:end]]
            # a column max is ~25x faster than a column argmax (1.6 against 38 ms at
            # 2048 x 2048): mutual pairs are read from the maxima after the last block
            np.maximum(column_max, block.max(axis=0), out=column_max)
            block[rows, best[start:end]] = np.iinfo(np.int32).min  # ours: mask in place
            second[start:end] = block.max(axis=1)
        mutual = first >= column_max[best]
        cosine = similarity.cosine
        # L2 distance of unit vectors: sqrt(2 - 2·cos)
        d_first = np.sqrt(np.maximum(2.0 - 2.0 * cosine * first, 0.0))
        d_second = np.sqrt(np.maximum(2.0 - 2.0 * cosine * second, 0.0))
        keep = (d_first < self.ratio * d_second) & mutual
        if self.min_similarity is not None:
            keep &= cosine * first > self.min_similarity
        rows = np.arange(n)
        return np.stack([rows[keep], best[keep]], axis=1).astype(np.int64)

    def match_many(
        self,
        query: LocalFeatures,
        references: Sequence[LocalFeatures],
        stop: Callable[[], bool] | None = None,
        spread: Spread | None = None,
    ) -> list[IntArray]:
        quantized = quantize_query(query.descriptors)  # once for every reference

        def match(_: LocalFeatures, reference: LocalFeatures) -> IntArray:
            return self._match(quantized, reference.descriptors)

        return match_each(match, query, references, stop, spread)
