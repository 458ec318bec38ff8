"""Estimator settings in typed groups. The defaults are those of Panek et al. 2025, "A Guide
to Structureless Visual Localization": a 12 px inlier threshold, LO-RANSAC with 1000 to 100000
iterations, a 2 px triangulation threshold for sparse features (8 px for dense ones). Every
threshold states its unit."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

from services.runtime.spare_workers import Spread


@dataclass(frozen=True)
class RansacOptions:
    """The robust loop (ours in ``services.estimators.ransac`` and PoseLib's alike).

    Attributes:
        max_error_px: inlier threshold on reprojection / epipolar (Sampson) error, pixels.
        min_iterations, max_iterations: LO-RANSAC iteration bounds; past ``min_iterations``,
            adaptive stopping decides. 100 (was 1000) halved e5p1's time on redkitchen
            (SIFT 105 -> 54 ms, XFeat 140 -> 118 ms a query) with the same recall within
            one query of 50 (``slloc eval --features xfeat,sift --estimators e5p1,auto``).
        success_prob: adaptive stopping: once an all-inlier sample was drawn with this
            probability.
        seed: seed of every random choice, for reproducible answers.
    """

    max_error_px: float = 12.0
    min_iterations: int = 100
    max_iterations: int = 100_000
    success_prob: float = 0.9999
    seed: int = 0


@dataclass(frozen=True)
class TriangulationOptions:
    """Points triangulated from the references through shared query keypoints (local
    triangulation, the refinement of ``motion_averaging``).

    Attributes:
        max_error_px: reprojection threshold of point triangulation, pixels: 2 for sparse
            features, 8 for dense ones.
        track_merge_px: query keypoints closer than this, in pixels, form one track (0 = exact
            equality, right for sparse detectors; 5 px suits dense matchers).
    """

    max_error_px: float = 2.0
    track_merge_px: float = 0.0


@dataclass(frozen=True)
class VerificationOptions:
    """When an estimator's pose counts as an answer: its support in matches, then in 3D
    (the pipeline's verification stage).

    Attributes:
        min_inliers: fewer inliers than this (over all references) is a failure.
        min_references: inliers must come from at least this many references.
        min_verified_points: fewer verified 3D points than this is a failure (0 disables the
            check): query keypoints that are inliers in >= 2 references whose reference
            observations triangulate to a point that reprojects into the query within
            ``RansacOptions.max_error_px`` (see ``services.estimators.verification``).
            Epipolar inliers alone do not prove a pose: unrelated images reach 40-75 of them.
        min_reference_spread_deg: estimators that take the position from the references'
            baselines (``e5p1``, ``essential_5pt``) answer ``degenerate_geometry`` when the
            references with inliers spread less than this many degrees around some direction
            as seen from the query, or lie on a line they look along
            (``services.estimators.position_conditioning``).
    """

    min_inliers: int = 30
    min_references: int = 2
    min_verified_points: int = 10
    min_reference_spread_deg: float = 3.0


@dataclass(frozen=True)
class FocalOptions:
    """Focal-length estimation for a query sent without intrinsics (``services.estimators.focal``).

    Attributes:
        min_points: fewer 2D–3D inliers than this (query keypoints ↔ points triangulated
            from the references) leave the focal length unobservable.
        max_relative_sigma: the focal length is unobservable when its standard deviation
            (pose-and-focal covariance) exceeds this fraction of it (default: 3σ within 5 %).
        halves_sigmas: … or when two random halves of the inliers give focal lengths
            that differ by more than this many standard deviations of their difference (2σ:
            each half has twice the variance).
        field_of_view_deg: plausible range of the longer side's field of view, degrees.
    """

    min_points: int = 30
    max_relative_sigma: float = 0.05 / 3.0
    halves_sigmas: float = 3.0
    field_of_view_deg: tuple[float, float] = (10.0, 150.0)


@dataclass(frozen=True)
class UncertaintyOptions:
    """The pose uncertainty reported with every localized answer, and how it caps the
    confidence (``services.estimators.uncertainty``).

    Attributes:
        min_points: fewer verified 3D points than this and no uncertainty is computed.
        max_position_3sigma_m: a 3σ (3 × RMS) position uncertainty above this, in map units
            (metres on a metric map), caps the confidence at ``capped_confidence``.
        max_rotation_3sigma_deg: the same for the rotation, degrees.
        max_disagreement_deg: ``auto``'s other verified pose turned more than this from the
            answer caps the confidence too (on redkitchen, 8 of 25 answers whose two poses
            were turned more than 4° apart were right, 7 of 8 at 3–4°). How far apart the
            two positions lie does not cap it: on redkitchen every pair more than 25 cm apart
            was also turned 6° or more, while on kitti05 E5+1's position along a straight road
            lay 0.3–10 m from local triangulation's with their rotations within 0.3°, and the
            answer was right in 31 of 31 such queries. The confidence model reads both.
        capped_confidence: the cap; also applied when no uncertainty could be computed for a
            pose whose focal length was estimated.
        target_position_m, target_rotation_deg: what the confidence is the probability of
            (the shipped confidence model's target): the confidence never exceeds the
            probability the uncertainty leaves for it (``within_target_probability``).
        reference_position_sigma_m, reference_rotation_sigma_deg: the spread of the
            references' own pose errors, per axis, that the uncertainty counts (map units and
            degrees; both must be positive for it to count, 0: the poses are exact). 1 cm and
            0.05° bring the errors within 3σ of the answer's uncertainty in 96–100 % of the
            localized answers on both dev sets, against 88–98 % with exact references.
    """

    min_points: int = 6
    max_position_3sigma_m: float = 0.25
    max_rotation_3sigma_deg: float = 5.0
    max_disagreement_deg: float = 4.0
    capped_confidence: float = 0.5
    target_position_m: float = 0.25
    target_rotation_deg: float = 5.0
    reference_position_sigma_m: float = 0.01
    reference_rotation_sigma_deg: float = 0.05


class PoseApproxMode(StrEnum):
    """How ``pose_approx`` combines the retrieved poses."""

    WEIGHTED = "weighted"  # retrieval-score-weighted interpolation
    TOP1 = "top1"  # the best-scoring reference's pose


@dataclass(frozen=True)
class PoseApproxOptions:
    mode: PoseApproxMode = PoseApproxMode.WEIGHTED


@dataclass(frozen=True)
class E3p1Options:
    """Attributes:
    metric_depth: depths in ``ReferenceObservation`` are metric (True) or known only up
        to one scale per image (False, e.g. monocular depth).
    """

    metric_depth: bool = True


@dataclass(frozen=True)
class EstimatorOptions:
    """Everything an estimator is told, by group; per-estimator groups are named after it.

    Attributes:
        time_budget_s: wall-clock budget of one ``estimate`` call in seconds (None =
            unbounded). The robust loops check it before every batch of hypotheses and cap
            PoseLib's iteration counts by it; a single PoseLib call is not interruptible, so the
            bound is soft by one call.
        spread: runs independent parts of the estimate (``auto``'s first-stage estimators) at
            once on the idle workers free at that moment (``SpareWorkers.split``); None: on
            the calling thread, one after the other. The answer is the same either way.
    """

    ransac: RansacOptions = field(default_factory=RansacOptions)
    triangulation: TriangulationOptions = field(default_factory=TriangulationOptions)
    verification: VerificationOptions = field(default_factory=VerificationOptions)
    time_budget_s: float | None = None
    pose_approx: PoseApproxOptions = field(default_factory=PoseApproxOptions)
    e3p1: E3p1Options = field(default_factory=E3p1Options)
    focal: FocalOptions = field(default_factory=FocalOptions)
    uncertainty: UncertaintyOptions = field(default_factory=UncertaintyOptions)
    spread: Spread | None = field(default=None, compare=False, repr=False)
