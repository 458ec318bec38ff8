"""Shared synthetic correspondences (exact ground truth, 1 px noise, 30 % outliers)."""

from __future__ import annotations

import pytest

from services.estimators.options import EstimatorOptions, RansacOptions
from tools.synthetic.correspondences import SyntheticCorrespondences, make_correspondences

# moderate sizes and capped iterations keep the module fast on two shared cores
MATCHES_PER_REFERENCE = 300
TEST_OPTIONS = EstimatorOptions(ransac=RansacOptions(min_iterations=100, max_iterations=2000))


@pytest.fixture(scope="session")
def scene() -> SyntheticCorrespondences:
    return make_correspondences(
        seed=7,
        num_references=10,
        matches_per_reference=MATCHES_PER_REFERENCE,
        noise_px=1.0,
        outlier_ratio=0.3,
        with_depth=True,
    )


@pytest.fixture(scope="session")
def coincident_scene() -> SyntheticCorrespondences:
    return make_correspondences(
        seed=8,
        num_references=5,
        matches_per_reference=150,
        with_depth=True,
        coincident_centers=True,
    )
