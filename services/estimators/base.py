"""The estimator contract: what every structureless pose estimator takes and returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING, Protocol

import numpy as np

from services.estimators.options import EstimatorOptions
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.types import BoolArray, FloatArray

if TYPE_CHECKING:
    from services.estimators.verification import CheckedTracks


class FailureReason(StrEnum):
    """Why a query was not localized. Values are API strings."""

    NO_REFERENCES = "no_references"  # the map is empty, or the prior excluded every image
    TOO_FEW_MATCHES = "too_few_matches"  # not enough correspondences for the solver
    DEGENERATE_GEOMETRY = "degenerate_geometry"  # e.g. all reference centres coincide
    NO_CONSENSUS = "no_consensus"  # the robust loop found too few inliers
    MISSING_DEPTH = "missing_depth"  # a depth estimator, but the query or no reference has depth
    TIME_BUDGET_EXCEEDED = "time_budget_exceeded"
    # no intrinsics were sent and the matches do not determine the focal length
    FOCAL_UNOBSERVABLE = "focal_unobservable"
    GRAVITY_MISMATCH = "gravity_mismatch"  # the pose disagrees with the query's gravity hint
    # several frames: frames localized alone disagree with the pose their session poses give
    INCONSISTENT_FRAMES = "inconsistent_frames"
    # a verified pose whose confidence is below the request's floor (the pose is the candidate)
    LOW_CONFIDENCE = "low_confidence"


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
    query_xy: FloatArray
    reference_xy: FloatArray
    retrieval_score: float = 0.0
    reference_depth: FloatArray | None = None
    query_depth: FloatArray | None = None

    @property
    def num_matches(self) -> int:
        return int(self.query_xy.shape[0])


@dataclass(frozen=True)
class EstimateResult:
    """What every estimator returns.

    Attributes:
        cam_from_world: the query pose, or None on failure.
        inliers: one (M_i,) bool mask per reference observation, over its matches.
        confidence: in [0, 1]; see ``confidence_from_inliers``.
        stats: numbers describing the run (iterations, inlier ratio, ...).
        failure_reason: set exactly when ``cam_from_world`` is None.
        estimator_used: the estimator whose answer this is, when another one chose it
            (``auto``); None when it is the estimator called.
        estimator_reason: why ``estimator_used`` was chosen (a short sentence), or None.
        structure: the 3D check of this pose's inlier tracks that ``verify_pose`` made, for
            the uncertainty to read instead of making it again (``structure_of``); None
            when the pose was not verified.
    """

    cam_from_world: Rigid3d | None
    inliers: list[BoolArray]
    confidence: float = 0.0
    stats: dict[str, float] = field(default_factory=dict)
    failure_reason: FailureReason | None = None
    estimator_used: str | None = None
    estimator_reason: str | None = None
    structure: CheckedTracks | None = field(default=None, compare=False, repr=False)

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
    needs_depth: bool  # needs depth for the query and the references

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult: ...
