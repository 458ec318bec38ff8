"""Synthetic global descriptors with neighbourhood structure, for retrieval tests and benchmarks.

I.i.d. random unit vectors in high dimension are all nearly orthogonal, so their "nearest
neighbours" past the first are noise that no index (and no real map) reproduces. Here each
descriptor is a view of a random *place*: ``normalize(place + noise)`` with noise of the
place's norm, so two views of one place have cosine ≈ 0.5 and views of different places ≈ 0.
"""

from __future__ import annotations

import numpy as np

from services.types import Float32Array, IntArray


def unit_rows(rng: np.random.Generator, n: int, dim: int) -> Float32Array:
    """(n, dim) i.i.d. random unit rows."""
    rows = rng.standard_normal((n, dim), dtype=np.float32)
    unit: Float32Array = rows / np.linalg.norm(rows, axis=1, keepdims=True)
    return unit


def place_views(rng: np.random.Generator, places: Float32Array, of: IntArray) -> Float32Array:
    """(len(of), D) unit views of ``places[of]`` ((P, D) unit rows)."""
    views = places[of] + unit_rows(rng, of.size, places.shape[1])
    unit: Float32Array = (views / np.linalg.norm(views, axis=1, keepdims=True)).astype(np.float32)
    return unit
