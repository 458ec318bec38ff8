"""The answer of a localization: the pose with its diagnostics, and the references that took
part in it."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from services.estimators.base import FailureReason, ReferenceObservation
from services.estimators.uncertainty import PoseUncertainty
from services.geometry.camera import Camera
from services.geometry.intrinsics_adaptation import CameraAdaptation
from services.geometry.rigid import Rigid3d
from services.types import BoolArray, FloatArray

# the least confidence of a localized answer: on both dev sets (five splits, sift and xfeat-lg)
# the lowest floor that turns away every answer more than 1 m off, and 14 of 1,365 right ones,
# all but one from queries outside the map's frames
# (docs/benchmarks/2026-11-30-reference-pose-spread.md)
DEFAULT_MIN_CONFIDENCE = 0.3


@dataclass(frozen=True)
class RetrievedReference:
    """A retrieved reference and how it took part: matches, inliers, and the inlier pixels
    ((K, 2) float64, COLMAP convention) in the query and in the reference."""

    image_id: str
    name: str
    score: float
    num_matches: int
    num_inliers: int
    query_xy: FloatArray
    reference_xy: FloatArray


@dataclass(frozen=True)
class SecondOpinion:
    """What the second configuration answered (``LocalizationResult.second_opinion``).

    Attributes:
        features: the configuration asked.
        localized, reason, confidence: its answer (the query's answer when it localized).
        agreed: both configurations withheld a pose below ``min_confidence`` and the two
            agree (``services.localization.second_opinion.agreed``).
        elapsed_ms: its time, the references' descriptions included.
        described: references it described from their originals (the others were kept).
    """

    features: str
    localized: bool
    reason: str | None
    confidence: float
    elapsed_ms: float
    described: int
    agreed: bool = False


@dataclass(frozen=True)
class LocalizationResult:
    """Attributes:
    estimator: the estimator asked for; ``estimator_used`` the one whose answer this is (the
        same, unless ``auto`` chose it, ``estimator_reason`` saying why).
    """

    localized: bool
    reason: str | None
    estimator: str
    cam_from_world: Rigid3d | None
    num_inliers: int
    confidence: float
    retrieved: list[RetrievedReference]
    timings_ms: dict[str, float]
    stats: dict[str, float]
    estimator_used: str | None = None
    estimator_reason: str | None = None
    camera: Camera | None = None  # the query camera used (None: no focal length determined)
    camera_source: str | None = None  # "request" or "estimated" (from the matches)
    uncertainty: PoseUncertainty | None = None
    camera_adaptation: CameraAdaptation | None = None  # how the request's camera was adapted
    upright_turn_deg: int = 0  # the clockwise turn of the upload the query was matched at
    # the pose of a ``low_confidence`` answer, which is not localized, and its uncertainty
    candidate: Rigid3d | None = None
    candidate_uncertainty: PoseUncertainty | None = None
    # what another feature configuration answered when the map's own found no answer
    # (``services.localization.second_opinion``)
    second_opinion: SecondOpinion | None = None

    @property
    def wider_retrieval(self) -> bool:
        """Whether the query was retrieved again with its references spread wider, its first
        answer being unsure (``services.localization.widen``)."""
        return self.stats.get("wider_retrieval", 0.0) > 0.0

    def below(self, min_confidence: float) -> LocalizationResult:
        """This answer, or, when it is localized with a confidence below ``min_confidence``,
        the ``low_confidence`` answer holding its pose as ``candidate``."""
        if not self.localized or self.confidence >= min_confidence:
            return self
        return replace(
            self,
            localized=False,
            reason=FailureReason.LOW_CONFIDENCE.value,
            cam_from_world=None,
            candidate=self.cam_from_world,
            uncertainty=None,
            candidate_uncertainty=self.uncertainty,
        )

    def raised(self, confidence: float) -> LocalizationResult:
        """This ``low_confidence`` answer localized at its candidate pose with ``confidence``."""
        if self.candidate is None:
            raise ValueError("only a low_confidence answer with a candidate pose can be raised")
        return replace(
            self,
            localized=True,
            reason=None,
            cam_from_world=self.candidate,
            candidate=None,
            uncertainty=self.candidate_uncertainty,
            candidate_uncertainty=None,
            confidence=confidence,
        )


def out_of_time(estimator: str, timings: dict[str, float]) -> LocalizationResult:
    """The answer of a localization whose time budget ran out before an estimate."""
    return LocalizationResult(
        localized=False,
        reason=FailureReason.TIME_BUDGET_EXCEEDED.value,
        estimator=estimator,
        cam_from_world=None,
        num_inliers=0,
        confidence=0.0,
        retrieved=[],
        timings_ms=dict(timings),
        stats={},
    )


def retrieved_references(
    observations: Sequence[ReferenceObservation],
    inliers: Sequence[BoolArray] | None,
    names: Mapping[str, str],
) -> list[RetrievedReference]:
    """How each matched reference took part: its inliers by ``inliers`` (one mask per
    observation; None: no inliers), its name by ``names`` (image id → name)."""
    retrieved = []
    for i, obs in enumerate(observations):
        mask = inliers[i] if inliers is not None else np.zeros(obs.num_matches, bool)
        retrieved.append(
            RetrievedReference(
                image_id=obs.image_id,
                name=names[obs.image_id],
                score=obs.retrieval_score,
                num_matches=obs.num_matches,
                num_inliers=int(mask.sum()),
                query_xy=obs.query_xy[mask],
                reference_xy=obs.reference_xy[mask],
            )
        )
    return retrieved
