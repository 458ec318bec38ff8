"""``unit`` of a gravity reading: any finite, non-zero length is a direction. A reading of
length 1e300 (its square overflows) or 1e-300 (its square underflows to 0) was refused with
"a direction must be a finite, non-zero vector" (a 422 on localize, found by the stateful
fuzz), though the published schema allows any length. Subnormal components are left out:
once onnxruntime or OpenCV is loaded, the CPU may flush them to zero (then refused)."""

from __future__ import annotations

import numpy as np
import pytest

from services.geometry.gravity import unit


@pytest.mark.parametrize(
    ("vector", "expected"),
    [
        ([0.0, 2.0, 0.0], [0.0, 1.0, 0.0]),
        ([3.0, 4.0, 0.0], [0.6, 0.8, 0.0]),
        ([0.0, 1e300, 1e300], [0.0, 2**-0.5, 2**-0.5]),
        ([0.0, -1e308, 0.0], [0.0, -1.0, 0.0]),
        ([1e-300, 0.0, 0.0], [1.0, 0.0, 0.0]),
    ],
)
def test_any_finite_non_zero_length_is_a_direction(
    vector: list[float], expected: list[float]
) -> None:
    with np.errstate(all="raise"):
        out = unit(np.array(vector))
    np.testing.assert_allclose(out, expected, atol=1e-15)
    assert np.linalg.norm(out) == pytest.approx(1.0, abs=1e-15)


@pytest.mark.parametrize(
    "vector", [[0.0, 0.0, 0.0], [-0.0, 0.0, 0.0], [np.nan, 1.0, 0.0], [np.inf, 0.0, 0.0]]
)
def test_zero_and_non_finite_vectors_are_refused(vector: list[float]) -> None:
    with pytest.raises(ValueError, match="finite, non-zero"):
        unit(np.array(vector))
