from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, Field

from app.schemas.estimators import EstimatorName
from app.schemas.geometry import CameraSchema, FiniteFloat, PoseSchema
from app.schemas.uncertainty import UncertaintyOut
from app.usecases.localize import LocalizeRequest
from services.estimators.base import FailureReason
from services.pipeline import LocalizationResult
from services.retrieval.search import PositionPrior


class PriorSchema(BaseModel):
    position: list[FiniteFloat] = Field(min_length=3, max_length=3)
    radius: float = Field(gt=0, allow_inf_nan=False)


class LocalizeParamsIn(BaseModel):
    """The ``params`` form field of a localize request (a JSON string; all optional)."""

    camera: CameraSchema | None = Field(
        None,
        description="Query intrinsics. When absent, the focal length is estimated from the "
        "matches (SIMPLE_PINHOLE, principal point at the image centre; answer camera_source "
        "'estimated'), or the answer is localized: false with reason focal_unobservable.",
    )
    estimator: EstimatorName | None = Field(
        None, description="Estimator name; default: the map's default_estimator"
    )
    top_k: int = Field(10, ge=1)
    prior: PriorSchema | None = None
    return_inliers: bool = False
    max_error_px: float | None = Field(
        None,
        gt=0,
        le=100,
        allow_inf_nan=False,
        description="Inlier threshold in pixels (default 12)",
    )
    time_budget_s: float | None = Field(
        None,
        gt=0,
        allow_inf_nan=False,
        description="Wall-clock budget in seconds, at most the service's "
        "(SLLOC_LOCALIZE_TIME_BUDGET_S, its default); past it the answer is localized: false "
        "with reason time_budget_exceeded",
    )

    def to_request(self) -> LocalizeRequest:
        prior = self.prior
        return LocalizeRequest(
            camera=self.camera.to_camera() if self.camera else None,
            estimator=self.estimator,
            top_k=self.top_k,
            prior=PositionPrior(np.array(prior.position), prior.radius) if prior else None,
            max_error_px=self.max_error_px,
            time_budget_s=self.time_budget_s,
        )


class RetrievedOut(BaseModel):
    image_id: str
    name: str
    score: float
    num_matches: int
    num_inliers: int


class InliersOut(BaseModel):
    image_id: str
    query_xy: list[list[float]] = Field(description="(K, 2) COLMAP pixel coordinates")
    reference_xy: list[list[float]]


class Timings(BaseModel):
    decode: float
    extract: float
    retrieve: float
    match: float
    estimate: float
    total: float


class LocalizeResult(BaseModel):
    localized: bool
    reason: FailureReason | None
    estimator: EstimatorName
    cam_from_world: PoseSchema | None
    camera_center: list[float] | None
    num_inliers: int
    confidence: float = Field(description="In [0, 1]; see README 'Reading the result'")
    retrieved: list[RetrievedOut]
    inliers: list[InliersOut] | None = None
    timings_ms: Timings
    camera: CameraSchema | None = Field(
        None, description="The query camera used: the request's, or the estimated one"
    )
    camera_source: Literal["request", "estimated"] | None = None
    uncertainty: UncertaintyOut | None = Field(
        None, description="Pose uncertainty; null without a pose or enough verified points"
    )

    @classmethod
    def from_result(cls, result: LocalizationResult, return_inliers: bool) -> LocalizeResult:
        """The answer to ``result``; per-reference inlier pixels only when ``return_inliers``."""
        pose = result.cam_from_world
        return cls(
            localized=result.localized,
            reason=FailureReason(result.reason) if result.reason is not None else None,
            estimator=result.estimator,
            cam_from_world=PoseSchema.from_rigid(pose) if pose is not None else None,
            camera_center=[float(v) for v in pose.center] if pose is not None else None,
            num_inliers=result.num_inliers,
            confidence=result.confidence,
            retrieved=[
                RetrievedOut(
                    image_id=r.image_id,
                    name=r.name,
                    score=r.score,
                    num_matches=r.num_matches,
                    num_inliers=r.num_inliers,
                )
                for r in result.retrieved
            ],
            inliers=[
                InliersOut(
                    image_id=r.image_id,
                    query_xy=r.query_xy.tolist(),
                    reference_xy=r.reference_xy.tolist(),
                )
                for r in result.retrieved
                if r.num_inliers > 0
            ]
            if return_inliers
            else None,
            timings_ms=Timings(**{k: round(v, 3) for k, v in result.timings_ms.items()}),
            camera=CameraSchema.from_camera(result.camera) if result.camera is not None else None,
            camera_source=result.camera_source,
            uncertainty=UncertaintyOut.from_uncertainty(result.uncertainty)
            if result.uncertainty is not None
            else None,
        )
