"""The single-frame localizer: decode → extract → retrieve → match → estimate → answer, with the
turn search for a query that may be sideways.

Reference images reach the localizer through a ``ReferenceStore`` (implemented by the database
layer), so the engine never touches SQL.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial

from services.confidence.model import ConfidenceModel, default_confidence_model
from services.errors import InvalidInputError
from services.estimators.base import FailureReason, PoseEstimator, ReferenceObservation
from services.estimators.options import EstimatorOptions
from services.estimators.registry import DEFAULT_ESTIMATOR, get_estimator
from services.features.base import FeatureExtractor, LocalFeatures
from services.geometry.camera import Camera, default_camera
from services.geometry.intrinsics_adaptation import rotate_points
from services.imaging.decode import (
    DecodedImage,
    check_pixel_limit,
    decode_image,
    decode_image_reduced,
)
from services.localization.answer import LocalizationResult, out_of_time, retrieved_references
from services.localization.clock import OutOfTimeError, StageClock
from services.localization.estimate import answer_pose
from services.localization.query_frame import (
    QueryFrame,
    QueryFrameHints,
    check_gravity,
    features_in_upload,
    resolve_query_frame,
    turn_image,
)
from services.localization.stages import (
    MatchedQuery,
    check_camera_matches,
    decode_depth_for,
    extract_full_size,
    match,
    retrieve,
)
from services.localization.turns import search_turns, searched_answer
from services.localization.widen import widen_unsure
from services.matching.base import Matcher
from services.matching.lightglue_onnx import OnnxLightGlueMatcher
from services.matching.refinement import (
    refine_reference_keypoints,
    refinement_image,
    refinement_side,
)
from services.references.images import ReferenceImageCache, reference_images
from services.references.store import ReferenceData, ReferenceStore, ReferenceView
from services.retrieval.base import GlobalDescriptor
from services.retrieval.search import PositionPrior
from services.retrieval.thinning import WIDER_SPACING_FACTOR
from services.runtime.memory import RequestShape, request_memory_mib
from services.runtime.spare_workers import SpareWorkers, Spread
from services.types import Float32Array, FloatArray, UInt8Array

logger = logging.getLogger(__name__)


def _default_estimator() -> PoseEstimator:
    return get_estimator(DEFAULT_ESTIMATOR)


@dataclass(frozen=True)
class LocalizeParams:
    """Attributes:
    estimator: the estimator (``services.estimators.registry.get_estimator`` resolves a name).
    time_budget_s: wall-clock budget of the whole localization in seconds (None =
        unbounded). It is checked after each stage (decode, extract, retrieve), before the
        match of each reference, between the turns searched and inside the estimate's long
        loops (focal estimation, the estimators' own, verification); once spent, the result
        is ``time_budget_exceeded``.
    frame: what an AR client says about its frame (camera rotation, gravity, rotation search).
    min_confidence: a pose with a lower confidence is no answer: ``localized`` False, reason
        ``low_confidence``, the pose as ``candidate``.
    """

    camera: Camera | None = None
    estimator: PoseEstimator = field(default_factory=_default_estimator)
    top_k: int = 10
    prior: PositionPrior | None = None
    options: EstimatorOptions = field(default_factory=EstimatorOptions)
    time_budget_s: float | None = None
    frame: QueryFrameHints = field(default_factory=QueryFrameHints)
    min_confidence: float = 0.0


@dataclass(frozen=True)
class DecodedQuery:
    """A query decoded: the upload's pixels, its frame (the camera adapted, the turns to try,
    gravity), the camera to estimate with (the default camera when the request has none) and
    the query's depth map."""

    image: UInt8Array
    frame: QueryFrame
    camera: Camera
    depth: Float32Array | None


class Localizer:
    """Owns the heavy components (extractor, matcher, global descriptor); thread-safe to call."""

    def __init__(
        self,
        extractor: FeatureExtractor,
        matcher: Matcher,
        global_descriptor: GlobalDescriptor,
        max_pixels: int,
        confidence_model: ConfidenceModel | None = None,
        reference_images: ReferenceImageCache | None = None,
    ) -> None:
        """``confidence_model``: turns a verified pose's stats into its confidence (None: the
        calibration shipped with the service). ``reference_images``: with it, the matches
        with each reference whose original the store keeps are refined to sub-pixel on the
        two images (``services.matching.refinement``), the images decoded kept there; None:
        matches stay at the keypoints."""
        self.extractor = extractor
        self.matcher = matcher
        self.global_descriptor = global_descriptor
        self.max_pixels = max_pixels
        self.confidence_model = confidence_model or default_confidence_model()
        self.reference_images = reference_images

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
            extractor,
            self.matcher,
            self.global_descriptor,
            self.max_pixels,
            self.confidence_model,
            self.reference_images,
        )

    def memory_mib(self, width: int, height: int, depth: bool, references: int = 0) -> float:
        """The memory a request computing with this localizer holds at its peak
        (``services.runtime.memory.request_memory_mib``): a ``width`` × ``height`` upload
        (with a depth map when ``depth``) decoded and described at this extractor's side and
        keypoints, and matched against ``references`` references (0: described only)."""
        scale = min(1.0, self.extractor.max_side / max(width, height, 1))
        lightglue = (
            self.matcher.lightglue_keypoints or self.extractor.max_keypoints
            if isinstance(self.matcher, OnnxLightGlueMatcher)
            else 0
        )
        return request_memory_mib(
            RequestShape(
                pixels=width * height,
                depth=depth,
                extracted_pixels=width * height * scale * scale,
                extractor=self.extractor.name,
                keypoints=self.extractor.max_keypoints,
                references=references,
                lightglue_keypoints=min(lightglue, self.extractor.max_keypoints),
            )
        )

    def upload_memory_mib(self, image_bytes: bytes, depth: bool, references: int = 0) -> float:
        """``memory_mib`` of the upload ``image_bytes``, its size read from its header.

        Raises:
            ImageTooLargeError: more than ``max_pixels`` pixels.
            ImageDecodeError: not a PNG or JPEG, or a truncated header.
        """
        width, height = check_pixel_limit(image_bytes, self.max_pixels)
        return self.memory_mib(width, height, depth, references)

    def describe_reference(
        self, image_bytes: bytes, camera: Camera, depth_bytes: bytes | None = None
    ) -> ReferenceData:
        """Decode and describe a reference image; checks the camera against the image size."""
        image = decode_image_reduced(image_bytes, self.max_pixels, self.extractor.max_side)
        check_camera_matches(camera, image)
        features = self.extract_features(image)
        return ReferenceData(
            features=features,
            global_descriptor=self.global_descriptor.compute(image.rgb, features),
            depth=decode_depth_for(depth_bytes, camera, self.max_pixels),
            feature_model=self.extractor.name,
            descriptor_model=self.global_descriptor.name,
        )

    def extract_features(self, image: DecodedImage) -> LocalFeatures:
        """Features of a (possibly reduced) decoded image in its full-size pixels."""
        return extract_full_size(self.extractor, image)

    def localize(
        self,
        image_bytes: bytes,
        params: LocalizeParams,
        store: ReferenceStore,
        depth_bytes: bytes | None = None,
        spare: SpareWorkers | None = None,
    ) -> LocalizationResult:
        """Localize the query with ``params.estimator``. The query is matched turned upright
        (``QueryFrame.turns``, best guess first); its other turns are tried while the answer
        is unsure (``services.localization.turns``), then a wider spread of references
        (``services.localization.widen``). Past one attempt, the stage timings are summed over
        the attempts.

        ``spare``: the idle workers the query's extraction, matching and estimate may borrow
        (None: they run on the calling thread alone)."""
        clock = StageClock(params.time_budget_s)
        try:
            query, first = self.start(image_bytes, params, store, depth_bytes, spare, clock)
        except OutOfTimeError:
            return out_of_time(params.estimator.name, clock.finish())

        def estimate(_: int, matched: MatchedQuery) -> LocalizationResult:
            return self.estimate(matched, query, params, params.estimator, clock, spare)

        results, attempts, upright = search_turns(
            query.frame.turns,
            first,
            lambda turn: self.match(query, turn, params, store, clock, spare),
            estimate,
            1,
            clock,
        )
        [result], [widened] = widen_unsure(
            results,
            upright,
            lambda matched: self.match_wider(query, matched, params, store, clock, spare),
            estimate,
            clock,
            params.options.ransac,
        )
        timings = clock.finish() if attempts > 1 or widened else result.timings_ms
        return searched_answer(
            result, attempts, widened, query.frame.adaptation, timings, params.min_confidence
        )

    def start(
        self,
        image_bytes: bytes,
        params: LocalizeParams,
        store: ReferenceStore,
        depth_bytes: bytes | None,
        spare: SpareWorkers | None,
        clock: StageClock,
    ) -> tuple[DecodedQuery, MatchedQuery]:
        """The query decoded and matched at its first turn.

        Raises:
            OutOfTimeError: the budget ran out.
        """
        query = self.decode(image_bytes, params, depth_bytes)
        clock.lap("decode")
        return query, self.match(query, query.frame.turns[0], params, store, clock, spare)

    def decode(
        self, image_bytes: bytes, params: LocalizeParams, depth_bytes: bytes | None
    ) -> DecodedQuery:
        """The decode stage of a query: its pixels, frame, camera and depth map."""
        image = decode_image(image_bytes, self.max_pixels)
        frame = resolve_query_frame(image_bytes, image, params.camera, params.frame)
        if self.extractor.rotation_invariant:
            # every turn matches as the first does: searching the others would only repeat it
            frame = replace(frame, turns=frame.turns[:1])
        camera = frame.camera or default_camera(image.shape[1], image.shape[0])
        return DecodedQuery(
            image, frame, camera, decode_depth_for(depth_bytes, camera, self.max_pixels)
        )

    def match(
        self,
        query: DecodedQuery,
        turn: int,
        params: LocalizeParams,
        store: ReferenceStore,
        clock: StageClock,
        spare: SpareWorkers | None,
    ) -> MatchedQuery:
        """Extract, retrieve and match with the upload turned clockwise by ``turn`` degrees;
        keypoints go back to the upload before estimation (the pose is the upload's).

        Raises:
            OutOfTimeError: the budget ran out after a stage.
        """
        turned = turn_image(query.image, turn)
        features = self.extractor.extract(turned, spare)
        clock.lap("extract")
        index = store.retrieval_index()
        top = retrieve(index, self.global_descriptor, turned, features, params.top_k, params.prior)
        references = store.load_references([image_id for image_id, _ in top])
        score_of = dict(top)
        clock.lap("retrieve")
        observations = self.match_references(
            query,
            turned,
            features,
            turn,
            [(ref, score_of[ref.image_id]) for ref in references],
            store,
            clock,
            spare,
        )
        clock.lap("match")  # before the matches are used: a stopped matcher matched fewer
        names = {ref.image_id: ref.name for ref in references}
        return MatchedQuery(query.camera, observations, names, turn, features)

    def match_wider(
        self,
        query: DecodedQuery,
        matched: MatchedQuery,
        params: LocalizeParams,
        store: ReferenceStore,
        clock: StageClock,
        spare: SpareWorkers | None,
    ) -> MatchedQuery | None:
        """``matched`` again, against references retrieved at the wider spacing
        (``WIDER_SPACING_FACTOR``); the references it already matched keep their matches.
        None when the wider retrieval brings no other reference.

        Raises:
            OutOfTimeError: the budget ran out after a stage.
        """
        turned = turn_image(query.image, matched.turn)
        index = store.retrieval_index()
        top = retrieve(
            index,
            self.global_descriptor,
            turned,
            matched.features,
            params.top_k,
            params.prior,
            WIDER_SPACING_FACTOR,
        )
        known = {observation.image_id: observation for observation in matched.observations}
        new = {image_id: score for image_id, score in top if image_id not in known}
        if not new:
            return None
        references = store.load_references(list(new))
        clock.lap("retrieve")
        observations = self.match_references(
            query,
            turned,
            matched.features,
            matched.turn,
            [(ref, new[ref.image_id]) for ref in references],
            store,
            clock,
            spare,
        )
        clock.lap("match")
        found = known | {observation.image_id: observation for observation in observations}
        ranked = [found[image_id] for image_id, _ in top if image_id in found]
        names = matched.names | {ref.image_id: ref.name for ref in references}
        return matched._replace(observations=ranked, names=names)

    def match_references(
        self,
        query: DecodedQuery,
        turned: UInt8Array,
        features: LocalFeatures,
        turn: int,
        references: list[tuple[ReferenceView, float]],
        store: ReferenceStore,
        clock: StageClock,
        spare: SpareWorkers | None,
    ) -> list[ReferenceObservation]:
        """The correspondences of the query (``features`` of the upload turned clockwise by
        ``turn`` degrees, ``turned``) with each of ``references`` (with its retrieval score)
        reached in the budget, refined where the configuration refines its matches."""
        observations = match(
            self.matcher,
            features,
            references,
            stop=clock.deadline.expired,
            spread=spare.split if spare is not None else None,
            observed=features_in_upload(features, turn),
            query_depth=query.depth,
        )
        height, width = query.image.shape[:2]
        return self.refine(
            turned,
            (turned.shape[1], turned.shape[0]),
            observations,
            [ref for ref, _ in references],
            store,
            clock,
            partial(rotate_points, rotation_deg=turn, width=width, height=height) if turn else None,
            spare.split if spare is not None else None,
        )

    def refine(
        self,
        rgb: UInt8Array,
        full_size: tuple[int, int],
        observations: list[ReferenceObservation],
        references: list[ReferenceView],
        store: ReferenceStore,
        clock: StageClock,
        query_points: Callable[[FloatArray], FloatArray] | None = None,
        spread: Spread | None = None,
    ) -> list[ReferenceObservation]:
        """``observations`` with their reference keypoints refined on the query image ``rgb``
        (an image of ``full_size`` (width, height), possibly decoded reduced), where the
        configuration refines its matches (``reference_images``); ``query_points`` maps the
        observations' query keypoints into it (None: they are in it); ``spread``: runs the
        references in parallel (None: one after the other)."""
        if self.reference_images is None or all(r.original_key is None for r in references):
            return observations  # nothing to refine against: the query image is not prepared
        side = refinement_side(self.extractor.max_side)
        return refine_reference_keypoints(
            refinement_image(rgb, *full_size, side),
            observations,
            reference_images(store, references, side, self.max_pixels, self.reference_images),
            clock.deadline.expired,
            query_points,
            spread,
        )

    def estimate(
        self,
        matched: MatchedQuery,
        query: DecodedQuery,
        params: LocalizeParams,
        estimator: PoseEstimator,
        clock: StageClock,
        spare: SpareWorkers | None = None,
    ) -> LocalizationResult:
        """Estimate and verify the pose of a matched query with ``estimator``, check it
        against the query's gravity, and answer it (timed on a branch of ``clock``).
        ``spare``: the idle workers the estimate may borrow."""
        clock = clock.branch()
        camera, observations, names, turn, _ = matched
        uncertainty = None
        camera_used: Camera | None = camera if params.camera is not None else None
        if not observations:
            outcome = None
            reason: str | None = FailureReason.NO_REFERENCES.value
        else:
            answer = answer_pose(
                estimator,
                camera,
                params.camera is None,
                observations,
                replace(
                    clock.bound(params.options), spread=spare.split if spare is not None else None
                ),
                clock.deadline,
                self.confidence_model,
            )
            outcome = check_gravity(
                answer.result, query.frame.gravity, params.frame.gravity, observations
            )
            camera_used = answer.camera
            if outcome.cam_from_world is not None:
                uncertainty = answer.uncertainty
            reason = outcome.failure_reason.value if outcome.failure_reason else None
        clock.lap("estimate", check=False)  # the work is done: its answer is kept
        pose = outcome.cam_from_world if outcome is not None else None
        return LocalizationResult(
            localized=pose is not None,
            reason=reason,
            estimator=estimator.name,
            cam_from_world=pose,
            num_inliers=outcome.num_inliers if outcome is not None and pose is not None else 0,
            confidence=outcome.confidence if outcome is not None else 0.0,
            retrieved=retrieved_references(
                observations, outcome.inliers if outcome is not None else None, names
            ),
            timings_ms=clock.finish(),
            stats=outcome.stats if outcome is not None else {},
            estimator_used=(outcome.estimator_used if outcome is not None else None)
            or estimator.name,
            estimator_reason=outcome.estimator_reason if outcome is not None else None,
            camera=camera_used,
            camera_source="estimated" if params.camera is None else "request",
            uncertainty=uncertainty,
            upright_turn_deg=turn,
        )
