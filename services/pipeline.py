"""The localizer: decode → extract → retrieve → match → estimate → result with diagnostics.

Reference images reach the pipeline through a ``ReferenceStore`` (implemented by the database
layer), so the engine never touches SQL.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from services.confidence.model import ConfidenceModel, default_confidence_model
from services.errors import InvalidInputError
from services.estimators.base import FailureReason, PoseEstimator, ReferenceObservation
from services.estimators.options import EstimatorOptions
from services.estimators.ransac import Deadline
from services.estimators.registry import DEFAULT_ESTIMATOR, get_estimator
from services.features.base import FeatureExtractor, LocalFeatures
from services.geometry.camera import Camera, default_camera
from services.geometry.intrinsics_adaptation import CameraAdaptation
from services.geometry.rigid import Rigid3d
from services.imaging import DecodedImage, decode_depth, decode_image, decode_image_reduced
from services.matching.base import Matcher
from services.pose_answer import answer_pose
from services.pose_uncertainty import PoseUncertainty
from services.query_frame import (
    QueryFrame,
    QueryFrameHints,
    check_gravity,
    features_in_upload,
    resolve_query_frame,
    turn_image,
)
from services.references import ReferenceData, ReferenceStore, ReferenceView
from services.retrieval.base import GlobalDescriptor
from services.retrieval.search import PositionPrior
from services.retrieval.thinning import search_thinned
from services.retrieval.vlad import encode
from services.runtime.spare_workers import SpareWorkers
from services.types import Float32Array, FloatArray, IntArray, UInt8Array

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class LocalizeParams:
    """Attributes:
    time_budget_s: wall-clock budget of the whole localization in seconds (None =
        unbounded). It is checked after each stage (decode, extract, retrieve) and before
        the match of each reference, and it bounds the estimator's own budget; once spent,
        the result is ``time_budget_exceeded``.
    frame: what an AR client says about its frame (camera rotation, gravity, rotation search).
    min_confidence: a pose with a lower confidence is no answer: ``localized`` False, reason
        ``low_confidence``, the pose as ``candidate``.
    """

    camera: Camera | None = None
    estimator: str = DEFAULT_ESTIMATOR
    top_k: int = 10
    prior: PositionPrior | None = None
    options: EstimatorOptions = field(default_factory=EstimatorOptions)
    time_budget_s: float | None = None
    frame: QueryFrameHints = field(default_factory=QueryFrameHints)
    min_confidence: float = 0.0


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
    # the pose of a ``low_confidence`` answer, which is not localized
    candidate: Rigid3d | None = None

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
        )


def _sample_depth(depth: Float32Array | None, xy: FloatArray) -> FloatArray | None:
    """Depth at (M, 2) COLMAP pixel coordinates (nearest pixel); None without a depth map."""
    if depth is None:
        return None
    h, w = depth.shape
    cols = np.clip(np.floor(xy[:, 0]).astype(np.int64), 0, w - 1)
    rows = np.clip(np.floor(xy[:, 1]).astype(np.int64), 0, h - 1)
    return depth[rows, cols].astype(np.float64)


class Localizer:
    """Owns the heavy components (extractor, matcher, global descriptor); thread-safe to call."""

    def __init__(
        self,
        extractor: FeatureExtractor,
        matcher: Matcher,
        global_descriptor: GlobalDescriptor,
        max_pixels: int,
        confidence_model: ConfidenceModel | None = None,
    ) -> None:
        """``confidence_model``: turns a verified pose's stats into its confidence (None: the
        calibration shipped with the service)."""
        self.extractor = extractor
        self.matcher = matcher
        self.global_descriptor = global_descriptor
        self.max_pixels = max_pixels
        self.confidence_model = confidence_model or default_confidence_model()

    def for_map(self, max_keypoints: int | None, max_side: int | None) -> Localizer:
        """This localizer with a map's keypoint budget and image size (None = the default).

        Raises:
            InvalidInputError: the extractor cannot honour them.
        """
        if max_keypoints is None and max_side is None:
            return self
        try:
            extractor = self.extractor.with_budget(max_keypoints, max_side)
        except ValueError as exc:
            raise InvalidInputError(f"map feature options: {exc}") from None
        return Localizer(
            extractor, self.matcher, self.global_descriptor, self.max_pixels, self.confidence_model
        )

    def describe_reference(
        self, image_bytes: bytes, camera: Camera, depth_bytes: bytes | None = None
    ) -> ReferenceData:
        """Decode and describe a reference image; checks the camera against the image size."""
        image = decode_image_reduced(image_bytes, self.max_pixels, self.extractor.max_side)
        _check_camera_matches(camera, image)
        depth = (
            decode_depth(depth_bytes, camera.width, camera.height, self.max_pixels)
            if depth_bytes is not None
            else None
        )
        features = self.extract_features(image)
        return ReferenceData(
            features=features,
            global_descriptor=self.global_descriptor.compute(image.rgb, features),
            depth=depth,
            feature_model=self.extractor.name,
            descriptor_model=self.global_descriptor.name,
        )

    def extract_features(self, image: DecodedImage) -> LocalFeatures:
        """Features of a (possibly reduced) decoded image in its full-size pixels."""
        return self.extractor.extract(image.rgb).at_full_size(
            image.factor, (image.width, image.height)
        )

    def localize(
        self,
        image_bytes: bytes,
        params: LocalizeParams,
        store: ReferenceStore,
        depth_bytes: bytes | None = None,
        spare: SpareWorkers | None = None,
    ) -> LocalizationResult:
        return self.localize_each(
            image_bytes, params, [params.estimator], store, depth_bytes, spare
        )[0]

    def localize_each(
        self,
        image_bytes: bytes,
        params: LocalizeParams,
        estimators: Sequence[str],
        store: ReferenceStore,
        depth_bytes: bytes | None = None,
        spare: SpareWorkers | None = None,
    ) -> list[LocalizationResult]:
        """Describe, retrieve and match the query once, then run each of ``estimators`` (names;
        ``params.estimator`` is not used) on the same matches: one result per estimator, as
        ``localize`` with that estimator answers. Each result has the shared stage timings and
        its own ``estimate`` time (``total`` leaves the other estimators out), and each
        estimator gets what is left of the time budget after matching.

        The query is matched turned upright (``QueryFrame.turns``, best guess first); the other
        turns are tried, while the budget lasts, for the estimators without a settled answer
        yet (confidence below ``SEARCH_CONFIDENCE``: a sideways image can give a pose from
        chance matches, which the confidence reads as wrong; and fewer than ``UPRIGHT_INLIERS``
        inliers, which a wrongly turned query does not reach), and each keeps its most
        confident answer (an answer that failed for want of depth is settled: no turn brings
        depth). A turn is estimated only when it matches ``TURN_MATCH_GAIN`` times more than
        every turn estimated before (learned descriptors match a wrongly turned image 5-10x
        less, rotation-invariant SIFT about as much: estimating it again would not change the
        answer). Past one attempt, every result has the shared stages summed over the attempts
        and its own estimation time summed over its own.

        ``spare``: the idle workers the query's extraction and matching may borrow (None: they
        run on the calling thread alone)."""
        chosen = [get_estimator(name) for name in estimators]
        clock = _StageClock(params.time_budget_s)
        try:
            image = decode_image(image_bytes, self.max_pixels)
            frame = resolve_query_frame(image_bytes, image, params.camera, params.frame)
            camera = frame.camera or default_camera(image.shape[1], image.shape[0])
            query_depth = (
                decode_depth(depth_bytes, camera.width, camera.height, self.max_pixels)
                if depth_bytes is not None
                else None
            )
            clock.lap("decode")
            matched = self._match(
                image, frame.turns[0], camera, query_depth, params, store, clock, spare
            )
        except _OutOfTimeError:
            timings = clock.finish()
            return [_out_of_time(estimator.name, timings) for estimator in chosen]
        own_ms = [0.0] * len(chosen)  # each estimator's own estimation time, all turns

        def estimate(index: int, matched: _MatchedQuery) -> LocalizationResult:
            start = time.perf_counter()
            result = self._estimate(matched, frame, params, chosen[index], clock.branch())
            own_ms[index] += (time.perf_counter() - start) * 1000.0
            return result

        results = [estimate(i, matched) for i in range(len(chosen))]
        clock.lap("estimate", check=False)
        attempts = 1
        most_matches = matched.num_matches
        for turn in frame.turns[1:]:  # other turns only while unsure, within the budget
            if all(_settled(r) for r in results) or clock.deadline.expired():
                break
            try:
                matched = self._match(image, turn, camera, query_depth, params, store, clock, spare)
            except _OutOfTimeError:
                break
            attempts += 1
            if matched.num_matches <= TURN_MATCH_GAIN * most_matches:
                continue  # no better matched than a turn already estimated: not upright
            most_matches = matched.num_matches
            results = [
                r if _settled(r) else _better(r, estimate(i, matched))
                for i, r in enumerate(results)
            ]
            clock.lap("estimate", check=False)
        summed = clock.finish() if attempts > 1 else None
        return [
            replace(
                r.below(params.min_confidence),
                camera_adaptation=frame.adaptation,
                timings_ms=_own_timings(summed, own) if summed else r.timings_ms,
                stats={**r.stats, "orientation_attempts": float(attempts)},
            )
            for r, own in zip(results, own_ms, strict=True)
        ]

    def _match(
        self,
        image: UInt8Array,
        turn: int,
        camera: Camera,
        query_depth: Float32Array | None,
        params: LocalizeParams,
        store: ReferenceStore,
        clock: _StageClock,
        spare: SpareWorkers | None,
    ) -> _MatchedQuery:
        """Extract, retrieve and match with the upload turned clockwise by ``turn`` degrees;
        keypoints go back to the upload before estimation (the pose is the upload's)."""
        lap = clock.lap
        turned = turn_image(image, turn)
        query = self.extractor.extract(turned, spare)
        lap("extract")
        index = store.retrieval_index()
        query_global = (
            encode(query.descriptors, index.vocabulary)
            if index.vocabulary is not None
            else self.global_descriptor.compute(turned, query)
        )
        rows, scores = search_thinned(index, query_global, params.top_k, params.prior)
        references = store.load_references([index.image_ids[i] for i in rows])
        score_of = {index.image_ids[i]: float(s) for i, s in zip(rows, scores, strict=True)}
        lap("retrieve")
        pairs = self.matcher.match_many(
            query,
            [ref.features for ref in references],
            stop=clock.deadline.expired,
            spread=spare.split if spare is not None else None,
        )
        lap("match")  # before the pairs are used: a stopped matcher returns fewer
        in_upload = features_in_upload(query, turn)
        observations = [
            _observe(in_upload, query_depth, ref, score_of[ref.image_id], ref_pairs)
            for ref, ref_pairs in zip(references, pairs, strict=True)
        ]
        return _MatchedQuery(camera, references, observations, turn)

    def _estimate(
        self,
        matched: _MatchedQuery,
        frame: QueryFrame,
        params: LocalizeParams,
        estimator: PoseEstimator,
        clock: _StageClock,
    ) -> LocalizationResult:
        camera, references, observations, turn = matched
        uncertainty = None
        camera_used: Camera | None = camera if params.camera is not None else None
        if not observations:
            outcome = None
            reason: str | None = FailureReason.NO_REFERENCES.value
        else:
            options = clock.bound(params.options)
            answer = answer_pose(
                estimator,
                camera,
                params.camera is None,
                observations,
                options,
                clock.deadline,
                self.confidence_model,
            )
            outcome = check_gravity(
                answer.result, frame.gravity, params.frame.gravity, observations
            )
            camera_used = answer.camera
            if outcome.cam_from_world is not None:
                uncertainty = answer.uncertainty
            reason = outcome.failure_reason.value if outcome.failure_reason else None
        clock.lap("estimate", check=False)  # the work is done: its answer is kept
        timings = clock.finish()

        retrieved = []
        for i, (ref, obs) in enumerate(zip(references, observations, strict=True)):
            mask = outcome.inliers[i] if outcome is not None else np.zeros(obs.num_matches, bool)
            retrieved.append(
                RetrievedReference(
                    image_id=ref.image_id,
                    name=ref.name,
                    score=obs.retrieval_score,
                    num_matches=obs.num_matches,
                    num_inliers=int(mask.sum()),
                    query_xy=obs.query_xy[mask],
                    reference_xy=obs.reference_xy[mask],
                )
            )
        pose = outcome.cam_from_world if outcome is not None else None
        return LocalizationResult(
            localized=pose is not None,
            reason=reason,
            estimator=estimator.name,
            cam_from_world=pose,
            num_inliers=outcome.num_inliers if outcome is not None and pose is not None else 0,
            confidence=outcome.confidence if outcome is not None else 0.0,
            retrieved=retrieved,
            timings_ms=timings,
            stats=outcome.stats if outcome is not None else {},
            estimator_used=(outcome.estimator_used if outcome is not None else None)
            or estimator.name,
            estimator_reason=outcome.estimator_reason if outcome is not None else None,
            camera=camera_used,
            camera_source="estimated" if params.camera is None else "request",
            uncertainty=uncertainty,
            upright_turn_deg=turn,
        )


class _MatchedQuery(NamedTuple):
    """A query described, its references retrieved and matched (at the clockwise ``turn`` of
    the upload, keypoints back in the upload): what every estimator takes."""

    camera: Camera
    references: list[ReferenceView]
    observations: list[ReferenceObservation]
    turn: int

    @property
    def num_matches(self) -> int:
        return sum(len(o.query_xy) for o in self.observations)


SEARCH_CONFIDENCE = 0.5  # an answer below it lets the other turns of the query be tried...
# ...unless it has this many inliers. Redkitchen, 25 queries, e5p1, search off: upright, the
# localized answers had 331-3587 inliers (xfeat-lg), 288-3885 (aliked-nn), 254-3570 (sift);
# turned a quarter, none of the xfeat-lg or aliked-nn queries localized (sift, rotation
# invariant, localized 11 with 208-1622, turned or not). Before this floor, 30-52 % of the
# redkitchen queries (upright, with 224-3238 inliers) paid for up to three more turns.
UPRIGHT_INLIERS = 200
# another turn is estimated only with this many times the matches of every turn estimated before
# (redkitchen, query against its best reference: XFeat 544-997 matches upright, 89-164 at the
# other turns; ALIKED 225-535 and 31-63; SIFT within 2 % at every turn)
TURN_MATCH_GAIN = 1.5


def _settled(result: LocalizationResult) -> bool:
    """No other turn of the query needs trying for this answer: it is confident, has so
    many inliers that the query was matched the right way up, or failed for want of depth,
    which no turn brings."""
    if result.reason == FailureReason.MISSING_DEPTH.value:
        return True
    return result.localized and (
        result.confidence >= SEARCH_CONFIDENCE or result.num_inliers >= UPRIGHT_INLIERS
    )


def _own_timings(summed: dict[str, float], own_estimate_ms: float) -> dict[str, float]:
    """One estimator's stage timings over several turns: the shared stages as ``summed``
    (all turns), its own estimation time instead of every estimator's, and ``total`` with
    the other estimators' time taken out."""
    others_ms = summed["estimate"] - own_estimate_ms
    return {**summed, "estimate": own_estimate_ms, "total": summed["total"] - others_ms}


def _better(a: LocalizationResult, b: LocalizationResult) -> LocalizationResult:
    """The localized one of two answers, the more confident when both are (``a`` on ties)."""
    if a.localized != b.localized:
        return a if a.localized else b
    return b if b.confidence > a.confidence else a


def _out_of_time(estimator: str, timings: dict[str, float]) -> LocalizationResult:
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


STAGES = ("decode", "extract", "retrieve", "match", "estimate")


class _OutOfTimeError(Exception):
    """The localization's time budget ran out between stages."""


class _StageClock:
    """Times the stages (milliseconds) and enforces the time budget between them."""

    def __init__(self, budget_s: float | None) -> None:
        self.deadline = Deadline(budget_s)
        self._budgeted = budget_s is not None
        self._left_at_lap = budget_s
        self._timings: dict[str, float] = {}
        self._start = self._lap_start = time.perf_counter()

    def lap(self, stage: str, check: bool = True) -> None:
        """Records ``stage`` as ended now (a stage run again adds up).

        Raises:
            _OutOfTimeError: ``check`` and the budget is spent.
        """
        now = time.perf_counter()
        self._timings[stage] = self._timings.get(stage, 0.0) + (now - self._lap_start) * 1000.0
        self._lap_start = now
        self._left_at_lap = self.deadline.remaining_s() if self._budgeted else None
        if check and self.deadline.expired():
            raise _OutOfTimeError

    def branch(self) -> _StageClock:
        """A clock that goes on from now as this one would, with the stages timed so far and
        what is left of the budget, as though the time since the last lap had not passed."""
        now = time.perf_counter()
        clone = _StageClock(None)
        clone.deadline = Deadline(self._left_at_lap)
        clone._timings = dict(self._timings)
        clone._start = now - (self._lap_start - self._start)
        clone._lap_start = now
        return clone

    def bound(self, options: EstimatorOptions) -> EstimatorOptions:
        """``options`` with an estimator budget no longer than what is left of this one."""
        left = self.deadline.remaining_s()
        if left == float("inf"):
            return options
        own = options.time_budget_s
        return replace(options, time_budget_s=max(0.0, left if own is None else min(own, left)))

    def finish(self) -> dict[str, float]:
        """The stage timings (0 for the stages not reached) and their ``total``."""
        timings = {stage: self._timings.get(stage, 0.0) for stage in STAGES}
        timings["total"] = (time.perf_counter() - self._start) * 1000.0
        return timings


def _observe(
    query: LocalFeatures,
    query_depth: Float32Array | None,
    ref: ReferenceView,
    score: float,
    pairs: IntArray,
) -> ReferenceObservation:
    """The correspondences of ``pairs`` ((M, 2) query/reference keypoint indices)."""
    query_xy = query.keypoints[pairs[:, 0]].astype(np.float64)
    reference_xy = ref.features.keypoints[pairs[:, 1]].astype(np.float64)
    return ReferenceObservation(
        image_id=ref.image_id,
        camera=ref.camera,
        cam_from_world=ref.cam_from_world,
        query_xy=query_xy,
        reference_xy=reference_xy,
        retrieval_score=score,
        reference_depth=_sample_depth(ref.depth, reference_xy),
        query_depth=_sample_depth(query_depth, query_xy),
    )


def _check_camera_matches(camera: Camera, image: DecodedImage) -> None:
    width, height = image.width, image.height
    if (camera.width, camera.height) != (width, height):
        raise InvalidInputError(
            f"camera is {camera.width}×{camera.height} but the image is {width}×{height}"
        )
