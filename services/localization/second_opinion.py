"""A second opinion: a query that its map's feature configuration retrieved references for but
could not localize, localized again by another configuration against those references,
described from their originals. The descriptions are kept for the next query that needs them
(the queries that fail together are usually taken together, where the map is weak)."""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import replace

from services.errors import InvalidInputError
from services.estimators.base import FailureReason
from services.estimators.options import RansacOptions, UncertaintyOptions
from services.estimators.ransac import searched_in_vain
from services.estimators.uncertainty import within_target_probability
from services.geometry.rigid import pose_error
from services.localization.answer import LocalizationResult, SecondOpinion
from services.localization.localizer import LocalizeParams, Localizer
from services.references.memory import MemoryReferenceStore
from services.references.store import ReferenceData, ReferenceView
from services.runtime.spare_workers import SpareWorkers

logger = logging.getLogger(__name__)

# the answers worth a second opinion: references were retrieved and matched, but the map's
# features did not verify a pose with them, or only a less confident one than was asked for
REASONS = frozenset(
    reason.value
    for reason in (
        FailureReason.TOO_FEW_MATCHES,
        FailureReason.NO_CONSENSUS,
        FailureReason.DEGENERATE_GEOMETRY,
        FailureReason.FOCAL_UNOBSERVABLE,
        FailureReason.LOW_CONFIDENCE,
    )
)


def wants_second_opinion(result: LocalizationResult, ransac: RansacOptions) -> bool:
    """Whether ``result`` failed in a way another configuration may not: references were
    retrieved, and its pose search did not draw every hypothesis ``ransac`` allows
    (``searched_in_vain``: an image of nothing in the map, which no second configuration
    localized on either development set; docs/benchmarks/2026-12-02-images-of-nothing.md)."""
    if result.localized or result.reason not in REASONS or not result.retrieved:
        return False
    return not searched_in_vain(result.stats, ransac)


# two configurations' withheld poses agree when they lie within this share of the confidence's
# target of each other (0.6 of 25 cm and 5°: 15 cm and 3°): on redkitchen's queries outside the
# map's frames every pair that close was within the target, and the closest pair with a wrong
# pose lay 25 cm apart (docs/benchmarks/2026-12-02-agreeing-opinions.md)
AGREEMENT_SHARE = 0.6


class DescribedCache:
    """References described by other configurations than their map's, by (extractor, image
    id); the ``capacity`` most recently used are kept. Thread-safe; two requests may describe
    the same reference at once, the later one's description is kept."""

    def __init__(self, capacity: int) -> None:
        if capacity < 0:
            raise ValueError(f"capacity must be >= 0, got {capacity}")
        self.capacity = capacity
        self._kept: OrderedDict[tuple[str, str], ReferenceData] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, extractor: str, image_id: str) -> ReferenceData | None:
        with self._lock:
            data = self._kept.get((extractor, image_id))
            if data is not None:
                self._kept.move_to_end((extractor, image_id))
            return data

    def put(self, extractor: str, image_id: str, data: ReferenceData) -> None:
        with self._lock:
            self._kept[(extractor, image_id)] = data
            self._kept.move_to_end((extractor, image_id))
            while len(self._kept) > self.capacity:
                self._kept.popitem(last=False)

    def __len__(self) -> int:
        with self._lock:
            return len(self._kept)


def ask(
    localizer: Localizer,
    features: str,
    image_bytes: bytes,
    params: LocalizeParams,
    references: Sequence[ReferenceView],
    read_original: Callable[[str], bytes | None],
    cache: DescribedCache,
    depth_bytes: bytes | None = None,
    spare: SpareWorkers | None = None,
) -> tuple[LocalizationResult, SecondOpinion] | None:
    """The query localized by ``localizer`` (the configuration ``features`` at its defaults)
    against ``references`` (those its first answer retrieved, best first), each described from
    its original (``read_original`` of its ``original_key``) unless ``cache`` holds it, with
    ``params`` at the query's upright guess alone and ``params.time_budget_s`` (the budget
    left) for the whole. None when no reference could be described in time (a reference
    without a readable original, or whose original does not fit its camera, is left out).
    """
    start = time.monotonic()
    deadline = start + params.time_budget_s if params.time_budget_s is not None else None
    originals: dict[str, str] = {}
    store = MemoryReferenceStore(lambda image_id: read_original(originals[image_id]))
    described = 0
    for view in references:
        if view.original_key is None:
            continue
        data = cache.get(localizer.extractor.name, view.image_id)
        if data is None:
            if deadline is not None and time.monotonic() >= deadline:
                break
            data = _describe(localizer, view, read_original(view.original_key))
            if data is None:
                continue
            cache.put(localizer.extractor.name, view.image_id, data)
            described += 1
        originals[view.image_id] = view.original_key
        store.add(view.name, view.camera, view.cam_from_world, data, view.image_id)
    if not originals:
        return None
    described_s = time.monotonic() - start
    budget = None if deadline is None else deadline - time.monotonic()
    if budget is not None and budget <= 0.0:
        return None
    again = replace(
        params,
        top_k=len(originals),
        prior=None,  # the references are those the prior kept
        time_budget_s=budget,
        frame=replace(params.frame, rotation_search=False),
    )
    result = localizer.localize(image_bytes, again, store, depth_bytes, spare)
    timings = dict(result.timings_ms)
    timings["extract"] = timings.get("extract", 0.0) + described_s * 1e3
    timings["total"] = timings.get("total", 0.0) + described_s * 1e3
    opinion = SecondOpinion(
        features=features,
        localized=result.localized,
        reason=result.reason,
        confidence=result.confidence,
        elapsed_ms=(time.monotonic() - start) * 1e3,
        described=described,
    )
    return replace(result, timings_ms=timings), opinion


def _describe(
    localizer: Localizer, view: ReferenceView, original: bytes | None
) -> ReferenceData | None:
    """``view`` described by ``localizer`` from its ``original``, with its stored depth map;
    None when there is no original or it does not fit the reference's camera."""
    if original is None:
        return None
    try:
        data = localizer.describe_reference(original, view.camera)
    except InvalidInputError as exc:
        logger.warning("second opinion: reference %s left out: %s", view.name, exc)
        return None
    return replace(data, depth=view.depth)


def agree(
    first: LocalizationResult, second: LocalizationResult, options: UncertaintyOptions
) -> bool:
    """Whether both answers withheld a pose (``low_confidence``) and the two lie within
    ``AGREEMENT_SHARE`` of the confidence's target (``options.target_position_m`` and
    ``target_rotation_deg``) of each other."""
    if first.candidate is None or second.candidate is None:
        return False
    position, rotation = pose_error(first.candidate, second.candidate)
    return (
        position <= AGREEMENT_SHARE * options.target_position_m
        and rotation <= AGREEMENT_SHARE * options.target_rotation_deg
    )


def agreed(
    first: LocalizationResult,
    second: LocalizationResult,
    min_confidence: float,
    options: UncertaintyOptions,
) -> LocalizationResult:
    """The more confident of two ``low_confidence`` answers that ``agree``, its confidence
    raised to ``options.capped_confidence`` — two configurations, each from its own keypoints
    and matches, found the same pose — yet never above the probability its uncertainty leaves
    for the target, nor below its own; localized at its candidate pose where that reaches
    ``min_confidence``, still withheld otherwise."""
    chosen = first if first.confidence >= second.confidence else second
    uncertainty = chosen.candidate_uncertainty
    raised = options.capped_confidence
    if uncertainty is not None:
        raised = min(raised, within_target_probability(uncertainty, options))
    confidence = max(chosen.confidence, raised)
    if confidence >= min_confidence:
        return chosen.raised(confidence)
    return replace(chosen, confidence=confidence)


def merged(
    first: LocalizationResult,
    second: LocalizationResult,
    opinion: SecondOpinion,
    min_confidence: float,
    options: UncertaintyOptions,
) -> LocalizationResult:
    """The query's answer: the second configuration's when it localized; when both withheld
    poses that ``agree``, the more confident raised (``agreed``), localized where that reaches
    ``min_confidence``; else the first's. With ``opinion`` and the two attempts' stage times
    summed."""
    timings = {
        stage: first.timings_ms.get(stage, 0.0) + second.timings_ms.get(stage, 0.0)
        for stage in dict.fromkeys([*first.timings_ms, *second.timings_ms])
    }
    if second.localized:
        answer = second
    elif agree(first, second, options):
        answer = agreed(first, second, min_confidence, options)
        opinion = replace(opinion, agreed=True)
    else:
        answer = first
    return replace(answer, timings_ms=timings, second_opinion=opinion)
