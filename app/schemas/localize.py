from __future__ import annotations

from pydantic import BaseModel, Field

from app.schemas.geometry import CameraSchema, FiniteFloat, PoseSchema
from app.schemas.maps import EstimatorName


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
    reason: str | None
    estimator: str
    cam_from_world: PoseSchema | None
    camera_center: list[float] | None
    num_inliers: int
    confidence: float = Field(description="In [0, 1]; see README 'Reading the result'")
    retrieved: list[RetrievedOut]
    inliers: list[InliersOut] | None = None
    timings_ms: Timings
