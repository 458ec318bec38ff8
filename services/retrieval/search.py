"""Top-k search by cosine similarity, optionally restricted by a position prior."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.retrieval.contracts import RetrievalIndex
from services.types import Float32Array, FloatArray, IntArray


@dataclass(frozen=True)
class PositionPrior:
    """Keep references whose camera centre lies within ``radius`` of ``position`` (world
    units); with ``up`` (a unit direction), the distance is measured across it only (a
    horizontal disc of any height, for a GPS fix)."""

    position: FloatArray
    radius: float
    up: FloatArray | None = None

    def distances(self, centers: FloatArray) -> FloatArray:
        """(N,) distance of each (N, 3) centre from ``position`` as the prior measures it."""
        offsets = centers - self.position
        if self.up is not None:
            offsets = offsets - np.outer(offsets @ self.up, self.up)
        return np.asarray(np.linalg.norm(offsets, axis=1), np.float64)


def top_k(
    query: Float32Array,
    descriptors: Float32Array,
    k: int,
    centers: FloatArray | None = None,
    prior: PositionPrior | None = None,
) -> tuple[IntArray, Float32Array]:
    """Indices and cosine scores of the ``k`` most similar references, best first.

    Args:
        query: (D,) unit vector.
        descriptors: (N, D) unit rows.
        k: how many to return (fewer when fewer qualify).
        centers: (N, 3) camera centres, needed with ``prior``.
        prior: drops references outside the prior's ball.
    Returns:
        (K,) int64 row indices into ``descriptors`` and (K,) float32 scores.
    """
    if descriptors.shape[0] == 0 or k <= 0:
        return np.zeros(0, np.int64), np.zeros(0, np.float32)
    scores = descriptors @ query
    candidates = np.arange(descriptors.shape[0])
    if prior is not None:
        if centers is None:
            raise ValueError("a position prior needs the reference camera centres")
        inside = prior.distances(centers) <= prior.radius
        candidates = candidates[inside]
    if candidates.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.float32)
    k = min(k, candidates.size)
    part = np.argpartition(-scores[candidates], k - 1)[:k]
    chosen = candidates[part]
    order = np.argsort(-scores[chosen], kind="stable")
    return chosen[order].astype(np.int64), scores[chosen[order]].astype(np.float32)


def search_index(
    index: RetrievalIndex, query: Float32Array, k: int, prior: PositionPrior | None = None
) -> tuple[IntArray, Float32Array]:
    """``top_k`` over ``index``: exact, or through its approximate index when it has one (with
    a prior, exact over the references inside it while they are fewer than the approximate
    index's ``min_references``).

    Returns:
        (K,) int64 row indices into ``index`` and (K,) float32 scores, best first.
    """
    if index.ann is None or k <= 0:
        return top_k(query, index.descriptors, k, index.centers, prior)
    if prior is None:
        return index.ann.search(query, k, index.descriptors)
    inside = prior.distances(index.centers) <= prior.radius
    rows = np.flatnonzero(inside)
    if rows.size < index.ann.index.options.min_references:
        chosen, scores = top_k(query, index.descriptors[rows], k)
        return rows[chosen], scores
    return index.ann.search(query, k, index.descriptors, inside)
