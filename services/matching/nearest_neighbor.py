"""Mutual nearest-neighbour matching with Lowe's ratio test on L2-normalised descriptors."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from services.features.base import LocalFeatures


class NearestNeighborMatcher:
    """Keeps a pair when each keypoint is the other's nearest neighbour and the nearest
    distance is below ``ratio`` × the second-nearest (in the query → reference direction)."""

    def __init__(self, ratio: float = 0.85) -> None:
        if not 0.0 < ratio <= 1.0:
            raise ValueError(f"ratio must be in (0, 1], got {ratio}")
        self.ratio = ratio
        self.name = f"mnn-ratio-{ratio:g}"

    def match(self, query: LocalFeatures, reference: LocalFeatures) -> NDArray[np.int64]:
        if len(query) < 2 or len(reference) < 2:
            return np.zeros((0, 2), dtype=np.int64)
        similarity = query.descriptors @ reference.descriptors.T
        # squared L2 distance of unit vectors: 2 - 2·cos
        nearest2 = np.argpartition(-similarity, 1, axis=1)[:, :2]
        rows = np.arange(len(query))
        s0 = similarity[rows, nearest2[:, 0]]
        s1 = similarity[rows, nearest2[:, 1]]
        swap = s1 > s0
        best = np.where(swap, nearest2[:, 1], nearest2[:, 0])
        first, second = np.maximum(s0, s1), np.minimum(s0, s1)
        d_first = np.sqrt(np.maximum(2.0 - 2.0 * first, 0.0))
        d_second = np.sqrt(np.maximum(2.0 - 2.0 * second, 0.0))
        keep = d_first < self.ratio * d_second
        mutual = np.argmax(similarity, axis=0)[best] == rows
        keep &= mutual
        return np.stack([rows[keep], best[keep]], axis=1).astype(np.int64)
