"""The reference layout of centres so far apart that their spread overflows float64: no
exception, the layout of no spread (no plan reads it as forward motion)."""

from __future__ import annotations

import numpy as np

from services.estimators.position_conditioning import reference_layout


def test_overflowing_spread_is_no_layout() -> None:
    centres = np.array([[0.0, 0.0, 0.0], [1e155, 0.0, 0.0], [0.0, 1e155, 0.0]])
    with np.errstate(over="ignore", invalid="ignore"):
        layout = reference_layout(centres, np.tile([0.0, 0.0, 1.0], (3, 1)), np.ones(3))
    assert layout.extent_m == 0.0 and not layout.forward_motion
