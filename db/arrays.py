"""numpy array ⇄ (dtype, shape, bytes) for the ``feature_arrays`` table."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from db.models import FeatureArray

ALLOWED_DTYPES = {"float16", "float32", "float64", "int32", "int64", "uint8", "uint16"}


def to_row(image_id: str, kind: str, array: NDArray[np.generic]) -> FeatureArray:
    dtype = array.dtype.name
    if dtype not in ALLOWED_DTYPES:
        raise ValueError(f"dtype {dtype} cannot be stored; allowed: {sorted(ALLOWED_DTYPES)}")
    data = np.ascontiguousarray(array).astype(array.dtype.newbyteorder("<"), copy=False)
    return FeatureArray(
        image_id=image_id, kind=kind, dtype=dtype, shape=list(array.shape), data=data.tobytes()
    )


def from_row(row: FeatureArray) -> NDArray[np.generic]:
    dtype = np.dtype(row.dtype).newbyteorder("<")
    return np.frombuffer(row.data, dtype=dtype).reshape(row.shape).astype(row.dtype)
