"""Which references a self-evaluation holds out, and which of the others stand in for the map
around each of them."""

from __future__ import annotations

import numpy as np

from services.types import FloatArray, IntArray


def spread_sample(centers: FloatArray, count: int) -> IntArray:
    """``count`` indices of ``centers`` ((N, 3)) spread over the map: farthest-point sampling
    from the centre nearest the centroid, so that every part of the map is held out about as
    often as its extent asks (deterministic; every index when ``count >= N``)."""
    n = len(centers)
    if count >= n:
        return np.arange(n)
    chosen = [int(np.argmin(np.linalg.norm(centers - centers.mean(axis=0), axis=1)))]
    distance = np.linalg.norm(centers - centers[chosen[0]], axis=1)
    while len(chosen) < count:
        farthest = int(np.argmax(distance))
        chosen.append(farthest)
        distance = np.minimum(distance, np.linalg.norm(centers - centers[farthest], axis=1))
    return np.asarray(chosen)


def held_out_map(centers: FloatArray, held_out: int, size: int, radius_m: float) -> IntArray:
    """The references a held-out one is localized against: the ``size`` nearest to it by
    centre, nearest first, of those farther than ``radius_m`` from it (0: all but itself). A
    local map: the references retrieval could reach around it, so that the cost of a held-out
    query does not grow with the map."""
    distance = np.linalg.norm(centers - centers[held_out], axis=1)
    near = distance <= radius_m
    near[held_out] = True
    order: IntArray = np.argsort(distance, kind="stable")
    kept: IntArray = order[~near[order]][:size]
    return kept
