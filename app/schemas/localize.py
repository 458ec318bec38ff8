from __future__ import annotations

import numpy as np
from pydantic import BaseModel, Field

from app.schemas.estimators import EstimatorName
from app.schemas.geometry import CameraSchema, FiniteFloat, PoseSchema
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
        description="Query intrinsics. When absent: SIMPLE_PINHOLE, focal 1.2 × the longer "
        "image side, principal point at the image centre.",
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
    estimator: EstimatorName = Field(description="The estimator asked for")
    estimator_used: EstimatorName = Field(
        description="The estimator whose answer this is: the one asked for, or the one `auto` chose"
    )
    estimator_reason: str | None = Field(
        None, description="Why `auto` chose `estimator_used` (null for the other estimators)"
    )
    cam_from_world: PoseSchema | None
    camera_center: list[float] | None
    num_inliers: int
    confidence: float = Field(description="In [0, 1]; see README 'Reading the result'")
    retrieved: list[RetrievedOut]
    inliers: list[InliersOut] | None = None
    timings_ms: Timings

    @classmethod
    def from_result(cls, result: LocalizationResult, return_inliers: bool) -> LocalizeResult:
        """The answer to ``result``; per-reference inlier pixels only when ``return_inliers``."""
        pose = result.cam_from_world
        return cls(
            localized=result.localized,
            reason=FailureReason(result.reason) if result.reason is not None else None,
            estimator=result.estimator,
            estimator_used=result.estimator_used or result.estimator,
            estimator_reason=result.estimator_reason,
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
        )
