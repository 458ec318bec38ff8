"""The inlier geometry the confidence reads: spread over the image and residual."""

from __future__ import annotations

import numpy as np

from services.confidence.rescoring import inlier_area_fraction


def test_area_fraction_counts_grid_cells() -> None:
    # 640×480 in an 8×8 grid: cells of 80×60 px
    xy = np.array([[1.0, 1.0], [79.0, 59.0], [81.0, 1.0], [639.9, 479.9], [700.0, -5.0]])
    # cells (0,0) twice, (0,1), (7,7); the point outside falls in the edge cell (0,7)
    assert inlier_area_fraction(xy, 640, 480) == 4 / 64
    assert inlier_area_fraction(np.zeros((0, 2)), 640, 480) == 0.0
    grid = np.stack(np.meshgrid(np.arange(8) * 80 + 40.0, np.arange(8) * 60 + 30.0), -1)
    assert inlier_area_fraction(grid.reshape(-1, 2), 640, 480) == 1.0
