"""Robust scale of residuals, for adaptive inlier thresholds in local optimisation."""

from __future__ import annotations

import numpy as np

from services.types import FloatArray


def adaptive_threshold_px(errors: FloatArray, max_error_px: float, floor_px: float = 1.0) -> float:
    """3σ of the errors below ``max_error_px`` (σ from the median, as for a Gaussian), clamped to
    [``floor_px``, ``max_error_px``]: the refinement set keeps the true inliers but drops the
    wrong matches that happen to pass the loose 12 px test."""
    below = errors[errors < max_error_px]
    if below.size == 0:
        return max_error_px
    sigma = 1.4826 * float(np.median(below))
    return float(min(max_error_px, max(floor_px, 3.0 * sigma)))
