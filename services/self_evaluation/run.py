"""One configuration's self-evaluation: each sampled reference localized, as a query with its
own camera, against a local map of the others described from their originals.

A held-out reference localized confidently where it is stored shows the place as its image
does; the references of its local map that cover it vote on whether they still match it
(``services.capture.freshness``), as a capture session's frames do."""

from __future__ import annotations

import logging
import math
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from services.capture.alignment import MIN_CONFIDENCE
from services.capture.freshness import (
    MIN_EVIDENCE,
    Vote,
    best_inliers,
    covering,
    frame_votes,
    reusable_inliers,
)
from services.capture.spacing import map_spacing
from services.errors import InvalidInputError
from services.estimators.base import PoseEstimator
from services.features.base import LocalFeatures
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d, pose_error
from services.localization.answer import LocalizationResult
from services.localization.localizer import LocalizeParams, Localizer
from services.references.memory import MemoryReferenceStore
from services.references.store import ReferenceData, ReferenceView
from services.runtime.worker_slots import WorkerSlots, holding
from services.self_evaluation.sample import held_out_map
from services.self_evaluation.summary import HeldOutAnswer
from services.types import FloatArray

logger = logging.getLogger(__name__)

# a held-out reference votes on the references that cover it when it was localized within
# this of its stored pose (position in metres, rotation in degrees)
VOTE_MAX_M = 0.25
VOTE_MAX_DEG = 2.0


@dataclass(frozen=True)
class MapReference:
    """A reference of the map as the self-evaluation sees it: its stored camera and pose are
    its ground truth as a query."""

    image_id: str
    name: str
    camera: Camera
    cam_from_world: Rigid3d


class Originals(Protocol):
    """The uploaded bytes of the map's references (the blob store in the service)."""

    def image(self, image_id: str) -> bytes: ...

    def depth(self, image_id: str) -> bytes | None: ...


class EvaluationCancelled(Exception):  # noqa: N818 (a signal, not an error)
    """The evaluation was stopped (its map deleted, the service shutting down)."""


@dataclass(frozen=True)
class HeldOutPlan:
    """Attributes:
    local_map: references each held-out one is localized against (its nearest by centre).
    radius_m: references within this distance of a held-out one are held out with it.
    top_k: references retrieved per query, as a localize request's ``top_k``.
    estimator: the estimator, as a localize request's.
    time_budget_s: each held-out query's budget, as a localize request's.
    """

    local_map: int
    radius_m: float
    top_k: int
    estimator: PoseEstimator
    time_budget_s: float | None


class DescribedReferences:
    """References described by one localizer from their originals, the most recently used
    ``capacity`` kept (held-out maps overlap: neighbours are described once while they are
    near the references held out)."""

    def __init__(self, localizer: Localizer, originals: Originals, capacity: int) -> None:
        self.localizer = localizer
        self.originals = originals
        self.capacity = capacity
        self._kept: OrderedDict[str, ReferenceData | None] = OrderedDict()

    def get(self, reference: MapReference) -> ReferenceData | None:
        """Its description, or None when its original cannot be read or described."""
        if reference.image_id in self._kept:
            self._kept.move_to_end(reference.image_id)
            return self._kept[reference.image_id]
        try:
            data: ReferenceData | None = self.localizer.describe_reference(
                self.originals.image(reference.image_id),
                reference.camera,
                self.originals.depth(reference.image_id),
            )
        except (InvalidInputError, LookupError, OSError) as exc:
            logger.warning("self-evaluation: reference %s left out: %s", reference.name, exc)
            data = None
        self._kept[reference.image_id] = data
        if len(self._kept) > self.capacity:
            self._kept.popitem(last=False)
        return data


def centers_of(references: Sequence[MapReference]) -> FloatArray:
    """(N, 3) camera centres of the references."""
    return np.stack([r.cam_from_world.center for r in references])


def evaluate(
    localizer: Localizer,
    references: Sequence[MapReference],
    sample: Sequence[int],
    originals: Originals,
    plan: HeldOutPlan,
    cache_capacity: int,
    slots: WorkerSlots | None = None,
    stopped: Callable[[], bool] = lambda: False,
    progress: Callable[[int], None] = lambda done: None,
    votes: list[Vote] | None = None,
) -> list[HeldOutAnswer]:
    """Localizes each ``references[i]`` of ``sample`` against its held-out map (``plan``),
    from its original, with its camera; ``progress(done)`` after each. ``slots`` are held
    around each description, each held-out query and each vote, with its memory (the
    localize workers'; None: unbounded). ``votes``: where the votes of the held-out
    references on those that cover them are appended (None: no votes).

    Raises:
        EvaluationCancelled: ``stopped()`` turned true.
    """
    centers = centers_of(references)
    spacing = map_spacing(centers)
    described = DescribedReferences(localizer, originals, cache_capacity)
    answers: list[HeldOutAnswer] = []
    for done, index in enumerate(sample, start=1):
        if stopped():
            raise EvaluationCancelled
        query = references[index]
        kept = held_out_map(centers, index, plan.local_map, plan.radius_m)
        store = MemoryReferenceStore(originals.image)
        local: list[str] = []  # the image ids in it
        nearest = math.inf
        for k in kept:
            reference = references[k]
            camera = reference.camera
            with holding(slots, localizer.memory_mib(camera.width, camera.height, False)):
                data = described.get(reference)
            if data is not None:
                nearest = min(nearest, float(np.linalg.norm(centers[k] - centers[index])))
                store.add(
                    reference.name,
                    reference.camera,
                    reference.cam_from_world,
                    data,
                    reference.image_id,
                )
                local.append(reference.image_id)
        width, height = query.camera.width, query.camera.height
        with holding(slots, localizer.memory_mib(width, height, False, plan.top_k)):
            localized = _localize(localizer, query, originals, store, plan)
        if localized is not None:
            answer, result = localized
            answers.append(replace(answer, nearest_reference_m=nearest))
            evidence = best_inliers(result)
            if votes is not None and spacing is not None and _votes_for_others(answer, evidence):
                with holding(slots, localizer.memory_mib(width, height, False, len(local))):
                    others = store.load_references(local)
                    votes += _votes(localizer, described, query, others, spacing, result, evidence)
        progress(done)
    return answers


def _votes_for_others(answer: HeldOutAnswer, evidence: int) -> bool:
    """Whether a held-out reference shows its place well enough to vote on the others: it
    localized confidently where it is stored, its best reference matched strongly."""
    return (
        answer.localized
        and answer.confidence >= MIN_CONFIDENCE
        and answer.within(VOTE_MAX_M, VOTE_MAX_DEG)
        and evidence >= MIN_EVIDENCE
    )


def _votes(
    localizer: Localizer,
    described: DescribedReferences,
    query: MapReference,
    others: list[ReferenceView],
    spacing: float,
    result: LocalizationResult,
    evidence: int,
) -> list[Vote]:
    """The votes of the held-out ``query`` on the references of its local map (``others``)
    that cover it (``services.capture.freshness.frame_votes``), from its localization
    (``result``) and against ``evidence`` (its best retrieved reference's inliers)."""
    near = covering(query.cam_from_world, [r.cam_from_world for r in others], spacing)

    def describe() -> LocalFeatures | None:
        data = described.get(query)
        return data.features if data is not None else None

    return frame_votes(
        query.name,
        query.camera,
        query.cam_from_world,
        [others[i] for i in near],
        reusable_inliers(result, query.camera),
        describe,
        localizer.matcher,
        evidence,
    )


def _localize(
    localizer: Localizer,
    query: MapReference,
    originals: Originals,
    store: MemoryReferenceStore,
    plan: HeldOutPlan,
) -> tuple[HeldOutAnswer, LocalizationResult] | None:
    """The held-out reference localized, and the localization's result; None when its
    original cannot be read."""
    try:
        image = originals.image(query.image_id)
    except (LookupError, OSError) as exc:
        logger.warning("self-evaluation: %s not held out: %s", query.name, exc)
        return None
    params = LocalizeParams(
        camera=query.camera,
        estimator=plan.estimator,
        top_k=plan.top_k,
        time_budget_s=plan.time_budget_s,
    )
    start = time.perf_counter()
    try:
        result = localizer.localize(image, params, store)
    except InvalidInputError as exc:
        logger.warning("self-evaluation: %s not held out: %s", query.name, exc)
        return None
    latency_ms = (time.perf_counter() - start) * 1e3
    position, rotation = float("inf"), float("inf")
    if result.localized and result.cam_from_world is not None:
        position, rotation = pose_error(result.cam_from_world, query.cam_from_world)
    return HeldOutAnswer(
        image_id=query.image_id,
        name=query.name,
        localized=result.localized,
        reason=result.reason,
        position_error_m=position,
        rotation_error_deg=rotation,
        confidence=result.confidence,
        num_inliers=result.num_inliers,
        latency_ms=latency_ms,
    ), result
