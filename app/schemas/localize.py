from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, Field

from app.schemas.ar import CameraAdaptationOut, FramePoseOut, GravityIn, OutputIn, PoseConvention
from app.schemas.estimators import EstimatorName
from app.schemas.geometry import CameraSchema, FiniteFloat, PoseSchema
from app.usecases.localize import LocalizeRequest
from services.estimators.base import FailureReason
from services.pipeline import LocalizationResult
from services.query_frame import QueryFrameHints
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
    # AR clients (README "Integrating an AR app")
    camera_rotation_deg: Literal[0, 90, 180, 270] | None = Field(
        None,
        description="Clockwise turn from the image `camera` describes to the upload as "
        "displayed (EXIF applied). Default: decided by the sizes (the camera may be given for "
        "any uniform scale of the upload) and EXIF, a swapped aspect taken as 90°",
    )
    gravity: GravityIn | None = None
    rotation_search: bool = Field(
        True,
        description="Without a gravity hint, also try the upload turned by 90°, 270° and 180° "
        "(within the time budget) when it fails as uploaded",
    )
    output: OutputIn = Field(default_factory=OutputIn)

    def to_request(self) -> LocalizeRequest:
        prior = self.prior
        return LocalizeRequest(
            camera=self.camera.to_camera() if self.camera else None,
            estimator=self.estimator,
            top_k=self.top_k,
            prior=PositionPrior(np.array(prior.position), prior.radius) if prior else None,
            max_error_px=self.max_error_px,
            time_budget_s=self.time_budget_s,
            frame=QueryFrameHints(
                self.camera_rotation_deg,
                self.gravity.to_hint() if self.gravity else None,
                self.rotation_search,
            ),
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
    # AR clients (README "Integrating an AR app")
    camera_adaptation: CameraAdaptationOut | None = Field(
        None, description="How `camera` was adapted to the upload (when a camera was given)"
    )
    upright_turn_deg: int = Field(
        0, description="Clockwise turn of the upload at which it was matched"
    )
    gravity_error_deg: float | None = Field(
        None, description="Angle between the gravity hint and the pose's (with a gravity hint)"
    )
    world_from_cam: dict[PoseConvention, FramePoseOut] | None = Field(
        None, description="The pose of `output.pose_of` in the conventions `output.frames`"
    )

    @classmethod
    def from_result(
        cls,
        result: LocalizationResult,
        return_inliers: bool,
        output: OutputIn | None = None,
    ) -> LocalizeResult:
        """The answer to ``result``; per-reference inlier pixels only when ``return_inliers``,
        camera-to-world as ``output`` asks."""
        pose = result.cam_from_world
        adaptation = result.camera_adaptation
        output = output or OutputIn()
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
            camera_adaptation=CameraAdaptationOut.from_adaptation(adaptation)
            if adaptation is not None
            else None,
            upright_turn_deg=result.upright_turn_deg,
            gravity_error_deg=result.stats.get("gravity_error_deg"),
            world_from_cam={
                f: FramePoseOut.from_pose(output.camera_pose(pose, adaptation), f)
                for f in output.frames
            }
            if pose is not None and output.frames
            else None,
        )
