"""Array type aliases of the engine; each use states its shape, e.g. ``(N, 2) FloatArray``."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
Float32Array = NDArray[np.float32]
IntArray = NDArray[np.int64]
Int32Array = NDArray[np.int32]
BoolArray = NDArray[np.bool_]
UInt8Array = NDArray[np.uint8]
