from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, Field

from app.schemas.ar import CameraAdaptationOut, FramePoseOut, GravityIn, OutputIn, PoseConvention
from app.schemas.estimators import EstimatorName
from app.schemas.geo import GeoPoseAccuracySchema, GeoPoseSchema, GpsSchema
from app.schemas.geometry import CameraSchema, FiniteFloat, PoseSchema
from app.schemas.session import MAX_FRAMES_SCHEMA, FrameIn, SessionAlignmentOut
from app.schemas.uncertainty import UncertaintyOut
from app.usecases.localize import LocalizeRequest
from app.usecases.localize_frames import SessionFrame
from services.estimators.base import FailureReason
from services.geo.geopose import GeoPose, GeoPoseAccuracy
from services.localization.answer import (
    DEFAULT_MIN_CONFIDENCE,
    LocalizationResult,
    RetrievedReference,
    SecondOpinion,
)
from services.localization.frames import SessionLocalizationResult
from services.localization.query_frame import QueryFrameHints
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
    gps: GpsSchema | None = Field(
        None,
        description="The device's GPS fix. On a geo-registered map, retrieval keeps the "
        "references within 3 × accuracy_m (default 10 m, at least 10 m) of it horizontally; "
        "422 on a map without a registration",
    )
    time_budget_s: float | None = Field(
        None,
        gt=0,
        allow_inf_nan=False,
        description="Wall-clock budget in seconds, at most the service's "
        "(SLLOC_LOCALIZE_TIME_BUDGET_S, its default); past it the answer is localized: false "
        "with reason time_budget_exceeded",
    )
    frames: list[FrameIn] | None = Field(
        None,
        min_length=1,
        max_length=MAX_FRAMES_SCHEMA,
        description="One entry per `image` part, in order: the frame's AR-session pose and "
        "optional camera. With frames the answer adds map_from_session and per-frame poses; "
        "two or more frames (at most SLLOC_MAX_FRAMES) are localized jointly. See the docs' AR "
        "page, 'Several frames'",
    )
    # AR clients (the docs' AR page, "Integrating an AR app")
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
    min_confidence: float = Field(
        DEFAULT_MIN_CONFIDENCE,
        ge=0,
        le=1,
        allow_inf_nan=False,
        description="A pose less confident than this is not an answer: localized: false, "
        "reason low_confidence, the pose as `candidate`. 0 answers every verified pose",
    )
    second_opinion: bool = Field(
        True,
        description="When the map's feature configuration retrieves references but does not "
        "localize the query (too_few_matches, no_consensus, degenerate_geometry, "
        "focal_unobservable, low_confidence), localize it again with the server's second "
        "configuration (SLLOC_SECOND_OPINION) against those references, within the time "
        "budget left; false answers at once. See the docs' API page, 'A second opinion'",
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
            frame=QueryFrameHints(
                self.camera_rotation_deg,
                self.gravity.to_hint() if self.gravity else None,
                self.rotation_search,
            ),
            min_confidence=self.min_confidence,
            second_opinion=self.second_opinion,
        )

    def to_frames(self) -> list[SessionFrame] | None:
        """The frames with their engine ``cam_from_session``; None without ``frames``."""
        if self.frames is None:
            return None
        return [
            SessionFrame(
                camera=frame.camera.to_camera() if frame.camera else None,
                cam_from_session=frame.session_pose.to_cam_from_session(),
            )
            for frame in self.frames
        ]


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


class SecondOpinionOut(BaseModel):
    """What the second configuration answered; the answer is its own when it localized."""

    features: str = Field(description="The feature configuration asked")
    localized: bool
    reason: FailureReason | None
    confidence: float
    elapsed_ms: float = Field(
        description="Its time, in timings_ms too: the references it described from their "
        "originals (counted in extract) and its localization"
    )
    described: int = Field(
        description="References it described from their originals (the others were kept from "
        "earlier second opinions)"
    )
    agreed: bool = Field(
        False,
        description="Both configurations withheld a pose below min_confidence and the two "
        "agree (within 15 cm and 3°): the answer is the more confident of them, its confidence "
        "raised to 0.5 at most as its uncertainty allows, localized where that reaches "
        "min_confidence",
    )

    @classmethod
    def from_opinion(cls, opinion: SecondOpinion) -> SecondOpinionOut:
        return cls(
            features=opinion.features,
            localized=opinion.localized,
            reason=FailureReason(opinion.reason) if opinion.reason is not None else None,
            confidence=opinion.confidence,
            elapsed_ms=round(opinion.elapsed_ms, 3),
            described=opinion.described,
            agreed=opinion.agreed,
        )


class FrameOut(BaseModel):
    """One uploaded frame of a query with session poses."""

    cam_from_world: PoseSchema | None
    camera_center: list[float] | None
    num_inliers: int = Field(description="Matches within the inlier threshold of its pose")
    num_point_inliers: int = Field(
        description="Its 2D–3D inliers in the joint estimate (0 for a single frame)"
    )
    retrieved: list[RetrievedOut]
    inliers: list[InliersOut] | None = None


def _retrieved_out(retrieved: list[RetrievedReference]) -> list[RetrievedOut]:
    return [
        RetrievedOut(
            image_id=r.image_id,
            name=r.name,
            score=r.score,
            num_matches=r.num_matches,
            num_inliers=r.num_inliers,
        )
        for r in retrieved
    ]


def _inliers_out(retrieved: list[RetrievedReference]) -> list[InliersOut]:
    return [
        InliersOut(
            image_id=r.image_id,
            query_xy=r.query_xy.tolist(),
            reference_xy=r.reference_xy.tolist(),
        )
        for r in retrieved
        if r.num_inliers > 0
    ]


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
    candidate: PoseSchema | None = Field(
        None,
        description="With reason low_confidence: the pose found, less confident than "
        "params.min_confidence (not an answer; `confidence` is its confidence)",
    )
    num_inliers: int
    confidence: float = Field(description="In [0, 1]; see the docs' API page, 'Reading the result'")
    retrieved: list[RetrievedOut]
    inliers: list[InliersOut] | None = None
    timings_ms: Timings
    geopose: GeoPoseSchema | None = Field(
        None, description="OGC GeoPose of the camera, on a geo-registered map when localized"
    )
    geopose_accuracy: GeoPoseAccuracySchema | None = None
    map_from_session: SessionAlignmentOut | None = Field(
        None,
        description="With params.frames, once localized: the transform from the AR session "
        "to the map (the docs' AR page, 'Several frames')",
    )
    frames: list[FrameOut] | None = Field(
        None, description="With params.frames: one per uploaded frame, in order"
    )
    camera: CameraSchema | None = Field(
        None, description="The query camera used: the request's, or the estimated one"
    )
    camera_source: Literal["request", "estimated"] | None = None
    uncertainty: UncertaintyOut | None = Field(
        None, description="Pose uncertainty; null without a pose or enough verified points"
    )
    # AR clients (the docs' AR page, "Integrating an AR app")
    camera_adaptation: CameraAdaptationOut | None = Field(
        None, description="How `camera` was adapted to the upload (when a camera was given)"
    )
    upright_turn_deg: int = Field(
        0, description="Clockwise turn of the upload at which it was matched"
    )
    wider_retrieval: bool = Field(
        False,
        description="Whether the query was retrieved a second time with its references spread "
        "wider, its first answer being below confidence 0.5; the answer is the more confident "
        "of the two (the docs' Models page, 'An unsure answer gets a wider spread')",
    )
    gravity_error_deg: float | None = Field(
        None, description="Angle between the gravity hint and the pose's (with a gravity hint)"
    )
    world_from_cam: dict[PoseConvention, FramePoseOut] | None = Field(
        None, description="The pose of `output.pose_of` in the conventions `output.frames`"
    )
    second_opinion: SecondOpinionOut | None = Field(
        None,
        description="When the map's configuration found no answer and another localized the "
        "query again (params.second_opinion): what it answered; null when none was asked",
    )

    @classmethod
    def from_result(
        cls,
        result: LocalizationResult,
        return_inliers: bool,
        geopose: tuple[GeoPose, GeoPoseAccuracy] | None = None,
        output: OutputIn | None = None,
    ) -> LocalizeResult:
        """The answer to ``result``; per-reference inlier pixels only when ``return_inliers``;
        the GeoPose when given; camera-to-world as ``output`` asks."""
        pose = result.cam_from_world
        adaptation = result.camera_adaptation
        output = output or OutputIn()
        return cls(
            localized=result.localized,
            reason=FailureReason(result.reason) if result.reason is not None else None,
            estimator=result.estimator,
            estimator_used=result.estimator_used or result.estimator,
            estimator_reason=result.estimator_reason,
            cam_from_world=PoseSchema.from_rigid(pose) if pose is not None else None,
            camera_center=[float(v) for v in pose.center] if pose is not None else None,
            candidate=PoseSchema.from_rigid(result.candidate)
            if result.candidate is not None
            else None,
            num_inliers=result.num_inliers,
            confidence=result.confidence,
            retrieved=_retrieved_out(result.retrieved),
            inliers=_inliers_out(result.retrieved) if return_inliers else None,
            timings_ms=Timings(**{k: round(v, 3) for k, v in result.timings_ms.items()}),
            geopose=GeoPoseSchema.from_geopose(geopose[0]) if geopose else None,
            geopose_accuracy=GeoPoseAccuracySchema.from_accuracy(geopose[1]) if geopose else None,
            camera=CameraSchema.from_camera(result.camera) if result.camera is not None else None,
            camera_source=result.camera_source,
            uncertainty=UncertaintyOut.from_uncertainty(result.uncertainty)
            if result.uncertainty is not None
            else None,
            camera_adaptation=CameraAdaptationOut.from_adaptation(adaptation)
            if adaptation is not None
            else None,
            upright_turn_deg=result.upright_turn_deg,
            wider_retrieval=result.wider_retrieval,
            gravity_error_deg=result.stats.get("gravity_error_deg"),
            world_from_cam={
                f: FramePoseOut.from_pose(output.camera_pose(pose, adaptation), f)
                for f in output.frames
            }
            if pose is not None and output.frames
            else None,
            second_opinion=SecondOpinionOut.from_opinion(result.second_opinion)
            if result.second_opinion is not None
            else None,
        )

    @classmethod
    def from_session_result(
        cls,
        result: SessionLocalizationResult,
        return_inliers: bool,
        geopose: tuple[GeoPose, GeoPoseAccuracy] | None = None,
        output: OutputIn | None = None,
    ) -> LocalizeResult:
        """The answer with ``map_from_session`` and ``frames``; the summary fields (and the
        GeoPose, of frame 0) as in ``SessionLocalizationResult.result``."""
        alignment = result.map_from_session
        return cls.from_result(result.result, return_inliers, geopose, output).model_copy(
            update={
                "map_from_session": SessionAlignmentOut.from_rigid(alignment)
                if alignment is not None
                else None,
                "frames": [
                    FrameOut(
                        cam_from_world=PoseSchema.from_rigid(f.cam_from_world)
                        if f.cam_from_world is not None
                        else None,
                        camera_center=[float(v) for v in f.cam_from_world.center]
                        if f.cam_from_world is not None
                        else None,
                        num_inliers=f.num_inliers,
                        num_point_inliers=f.num_point_inliers,
                        retrieved=_retrieved_out(f.retrieved),
                        inliers=_inliers_out(f.retrieved) if return_inliers else None,
                    )
                    for f in result.frames
                ],
            }
        )
