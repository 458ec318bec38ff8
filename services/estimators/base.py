"""The estimator contract: what every structureless pose estimator takes and returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d


class FailureReason(StrEnum):
    """Why a query was not localized. Values are API strings."""

    NO_REFERENCES = "no_references"  # the map is empty, or the prior excluded every image
    TOO_FEW_MATCHES = "too_few_matches"  # not enough correspondences for the solver
    DEGENERATE_GEOMETRY = "degenerate_geometry"  # e.g. all reference centres coincide
    NO_CONSENSUS = "no_consensus"  # the robust loop found too few inliers
    TIME_BUDGET_EXCEEDED = "time_budget_exceeded"


@dataclass(frozen=True)
class ReferenceObservation:
    """One retrieved reference image and its correspondences with the query.

    Attributes:
        image_id: id of the reference image.
        camera: its camera.
        cam_from_world: its pose.
        query_xy: (M, 2) float64 query keypoints, COLMAP pixel convention.
        reference_xy: (M, 2) float64 matching reference keypoints, COLMAP pixel convention.
        retrieval_score: cosine similarity of the global descriptors.
        reference_depth: (M,) float64 depth in metres at ``reference_xy`` (0 = unknown), or None.
        query_depth: (M,) float64 depth in metres at ``query_xy`` (0 = unknown), or None.
    """

    image_id: str
    camera: Camera
    cam_from_world: Rigid3d
    query_xy: NDArray[np.float64]
    reference_xy: NDArray[np.float64]
    retrieval_score: float = 0.0
    reference_depth: NDArray[np.float64] | None = None
    query_depth: NDArray[np.float64] | None = None

    @property
    def num_matches(self) -> int:
        return int(self.query_xy.shape[0])


@dataclass(frozen=True)
class EstimatorOptions:
    """Robust-estimation settings; the defaults follow the structureless-localization guide.

    Attributes:
        max_error_px: inlier threshold on reprojection / epipolar (Sampson) error, pixels.
        min_iterations, max_iterations: LO-RANSAC iteration bounds.
        min_inliers: fewer inliers than this (over all references) is a failure.
        min_references: inliers must come from at least this many references.
        min_verified_points: fewer verified 3D points than this is a failure (0 disables the
            check): query keypoints that are inliers in >= 2 references whose reference
            observations triangulate to a point that reprojects into the query within
            ``max_error_px`` (see ``services.estimators.verification``). Epipolar inliers alone
            do not prove a pose: unrelated images reach 40-75 of them.
        seed: seed of every random choice, for reproducible answers.
        time_budget_s: wall-clock budget of one ``estimate`` call in seconds (None = unbounded).
            Estimators check it between solver calls and cap their own iteration counts; a
            single PoseLib call is not interruptible, so the bound is soft by one call.
        triangulation_error_px: reprojection threshold of point triangulation (local
            triangulation, LazyLoc refinement): 2 px for sparse features, 8 px for dense ones.
        track_merge_px: query keypoints closer than this form one track (0 = exact equality,
            right for sparse detectors; the guide uses 5 px for dense matchers).
        metric_depth: depths in ``ReferenceObservation`` are metric (True) or known only up to
            one scale per image (False, e.g. monocular depth); used by ``e3p1``.
        pose_approx_mode: ``"weighted"`` (retrieval-score-weighted interpolation) or ``"top1"``.
    """

    max_error_px: float = 12.0
    min_iterations: int = 1000
    max_iterations: int = 100_000
    min_inliers: int = 30
    min_references: int = 2
    min_verified_points: int = 10
    seed: int = 0
    time_budget_s: float | None = None
    triangulation_error_px: float = 2.0
    track_merge_px: float = 0.0
    metric_depth: bool = True
    pose_approx_mode: str = "weighted"


@dataclass(frozen=True)
class EstimateResult:
    """What every estimator returns.

    Attributes:
        cam_from_world: the query pose, or None on failure.
        inliers: one (M_i,) bool mask per reference observation, over its matches.
        confidence: in [0, 1]; see ``confidence_from_inliers``.
        stats: numbers describing the run (iterations, inlier ratio, ...).
        failure_reason: set exactly when ``cam_from_world`` is None.
    """

    cam_from_world: Rigid3d | None
    inliers: list[NDArray[np.bool_]]
    confidence: float = 0.0
    stats: dict[str, float] = field(default_factory=dict)
    failure_reason: FailureReason | None = None

    @property
    def num_inliers(self) -> int:
        return int(sum(int(mask.sum()) for mask in self.inliers))

    @classmethod
    def failure(
        cls,
        reason: FailureReason,
        references: list[ReferenceObservation],
        stats: dict[str, float] | None = None,
    ) -> EstimateResult:
        masks = [np.zeros(ref.num_matches, dtype=bool) for ref in references]
        return cls(None, masks, 0.0, stats or {}, reason)


def confidence_from_inliers(num_inliers: int, num_references_with_inliers: int) -> float:
    """Heuristic confidence in [0, 1): grows with the inlier count (half at 50 inliers) and is
    scaled down when the inliers come from a single reference (scale then rests on few points).
    """
    spread = min(num_references_with_inliers, 3) / 3.0
    return float(num_inliers / (num_inliers + 50.0) * spread)


class PoseEstimator(Protocol):
    """Estimates the query's ``cam_from_world`` from its correspondences with posed references."""

    name: str

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult: ...
