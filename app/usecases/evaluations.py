"""Self-evaluation of a map: a spread of its own references is localized, each against the
rest of the map, for each feature configuration asked for; what it measures is stored with
the configuration it recommends (``services/self_evaluation``).

Evaluations run one at a time on a background thread at the lowest CPU priority; an evaluation
a restart interrupted runs again from its start. Each configuration is measured with the
server's localizer for it (``services.components.Localizers``), loaded on first use and kept.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from functools import partial
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from app.usecases.auto_features import AutoEvaluation
from app.usecases.errors import ConflictError, NotFoundError
from app.usecases.freshness import flag_stale
from app.usecases.maps import require_map
from db.blobs import BlobStore
from db.models import Map, MapEvaluation
from db.repositories.evaluations import EvaluationRepository
from db.repositories.maps import lock_map_row
from db.store import camera_of, pose_of, unusable
from services.capture.freshness import Vote
from services.components import Localizers
from services.errors import InvalidInputError
from services.estimators.registry import get_estimator
from services.features.configs import get_feature_config
from services.references.cache import ReferenceFeatureCache
from services.retrieval.training import BackgroundTrainer
from services.runtime.memory import EVALUATION_DESCRIBED
from services.runtime.worker_slots import WorkerSlots
from services.self_evaluation.run import (
    EvaluationCancelled,
    HeldOutPlan,
    MapReference,
    centers_of,
    evaluate,
)
from services.self_evaluation.sample import spread_sample
from services.self_evaluation.summary import recommend, summarize

logger = logging.getLogger(__name__)

# references held out by default, and at most
DEFAULT_SAMPLE = 30
MAX_SAMPLE = 200
# references a held-out one is localized against: its nearest (a local map)
LOCAL_MAP = 40
# maps whose latest results are kept for /metrics (the most recently evaluated)
LATEST_KEPT = 1000
# each held-out query's time budget (seconds), as a localize request's
QUERY_BUDGET_S = 10.0


@dataclass(frozen=True)
class EvaluationRequest:
    """What an evaluation measures: ``configurations`` (feature presets; None: every one
    ``evaluable`` lists), the references held out, those held out with each, the references
    retrieved per query and the estimator (None: the map's default)."""

    configurations: tuple[str, ...] | None = None
    sample_size: int = DEFAULT_SAMPLE
    holdout_radius_m: float = 0.0
    top_k: int = 10
    estimator: str | None = None

    @classmethod
    def stored(cls, values: dict[str, Any]) -> EvaluationRequest:
        """The request as ``start_evaluation`` stored it (configurations resolved)."""
        return cls(
            configurations=tuple(values["configurations"]),
            sample_size=int(values["sample_size"]),
            holdout_radius_m=float(values["holdout_radius_m"]),
            top_k=int(values["top_k"]),
            estimator=values.get("estimator"),
        )


def start_evaluation(
    sessions: sessionmaker[Session],
    localizers: Localizers,
    map_id: str,
    request: EvaluationRequest,
    evaluator: Evaluator | None,
) -> MapEvaluation:
    """Stores a queued evaluation of the map and schedules it. It may measure the
    configurations the server serves (``localizers.choices``: its own and those of
    ``SLLOC_EVALUATION_FEATURES`` whose models are built), by default every one.

    Raises:
        NotFoundError: unknown map.
        InvalidInputError: an unknown configuration or estimator, one not allowed, or one
            whose models are not built.
        ConflictError: the map is being evaluated, or has fewer than two references with
            their originals.
    """
    configurations = _configurations(localizers, request)
    with sessions.begin() as session:
        row = _queue(session, map_id, request, configurations)
        session.expunge(row)
    if evaluator is not None:
        evaluator.schedule(row.id)
    return row


def _configurations(localizers: Localizers, request: EvaluationRequest) -> list[str]:
    """The configurations the request measures, checked against those the server serves.

    Raises:
        InvalidInputError: an unknown configuration or estimator, one not allowed, or one
            whose models are not built.
    """
    configurations = list(request.configurations or localizers.choices)
    for name in configurations:
        get_feature_config(name)  # unknown: 422
        problem = localizers.unavailable.get(name)
        if problem:
            raise InvalidInputError(f"configurations: {name} cannot run on this server: {problem}")
        if name not in localizers.choices:
            raise InvalidInputError(
                f"configurations: {name} is not measured on this server: it measures "
                f"{', '.join(localizers.choices)} (SLLOC_FEATURES and "
                "SLLOC_EVALUATION_FEATURES)"
            )
    if request.estimator is not None:
        get_estimator(request.estimator)
    return configurations


def _queue(
    session: Session, map_id: str, request: EvaluationRequest, configurations: list[str]
) -> MapEvaluation:
    """Stores a queued evaluation of the map in ``session``'s transaction.

    Raises:
        NotFoundError: unknown map.
        ConflictError: the map is being evaluated, or has fewer than two references with
            their originals.
    """
    map_row = require_map(session, map_id)
    lock_map_row(session, map_id)  # one of two concurrent starts sees the other's
    repository = EvaluationRepository(session)
    running = repository.active(map_id)
    if running is not None:
        raise ConflictError(f"the map is being evaluated already: evaluation {running.id}")
    if repository.reference_count(map_id) < 2:
        raise ConflictError("a self-evaluation needs at least two references with their originals")
    stored = asdict(replace(request, configurations=tuple(configurations)))
    # the map's revision, to tell when it has changed enough to be evaluated again
    stored |= {"configurations": configurations, "revision": map_row.revision}
    return repository.create(map_id, stored)


def get_evaluation(
    sessions: sessionmaker[Session], map_id: str, evaluation_id: str
) -> MapEvaluation:
    """Raises: NotFoundError: no such map, or no such evaluation of it."""
    with sessions() as session:
        require_map(session, map_id)
        row = EvaluationRepository(session).get(map_id, evaluation_id)
        if row is None:
            raise NotFoundError("evaluation", evaluation_id)
        session.expunge(row)
        return row


def list_evaluations(
    sessions: sessionmaker[Session], map_id: str, offset: int, limit: int
) -> tuple[list[MapEvaluation], int]:
    """The map's evaluations, newest first. Raises: NotFoundError: no such map."""
    with sessions() as session:
        require_map(session, map_id)
        rows, total = EvaluationRepository(session).page(map_id, offset, limit)
        session.expunge_all()
        return rows, total


def cancel_evaluation(sessions: sessionmaker[Session], map_id: str, evaluation_id: str) -> None:
    """Stops an unfinished evaluation (it ends ``cancelled``); a finished one is deleted.

    Raises:
        NotFoundError: no such map, or no such evaluation of it.
    """
    with sessions.begin() as session:
        require_map(session, map_id)
        repository = EvaluationRepository(session)
        row = repository.get(map_id, evaluation_id)
        if row is None:
            raise NotFoundError("evaluation", evaluation_id)
        if not repository.set_state(evaluation_id, "cancelled"):
            session.delete(row)


class _BlobOriginals:
    """The originals of one map's references, read from the blob store by image id."""

    def __init__(self, blobs: BlobStore, keys: dict[str, tuple[str, str | None]]) -> None:
        self.blobs = blobs
        self.keys = keys

    def image(self, image_id: str) -> bytes:
        return self.blobs.get(self.keys[image_id][0])

    def depth(self, image_id: str) -> bytes | None:
        key = self.keys[image_id][1]
        return self.blobs.get(key) if key is not None else None


class Evaluator:
    """Runs the stored evaluations, one at a time, and keeps the latest results of the maps
    evaluated since start-up (for ``/metrics``)."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        localizers: Localizers,
        blobs: BlobStore,
        slots: WorkerSlots | None = None,
        auto: AutoEvaluation | None = None,
        features_cache: ReferenceFeatureCache | None = None,
    ) -> None:
        """``slots``: held around each description and held-out query with its memory (an
        evaluation computes in a localize worker's place; None: unbounded);
        ``auto``: when maps with ``features: auto`` are evaluated on their own and what
        follows a finished evaluation (None: only evaluations asked for run);
        ``features_cache``: the served features, whence stale references the map retires
        are dropped."""
        self.sessions = sessions
        self.features_cache = features_cache
        self.slots = slots
        self.localizers = localizers
        self.auto = auto
        self.blobs = blobs
        self.worker = BackgroundTrainer("self-evaluation")
        self.finished: dict[str, int] = {}  # evaluations ended since start-up, by state
        self.held_out = 0  # held-out queries localized since start-up
        # map id -> (map name, configuration -> summary) of its latest evaluation
        self.latest: dict[str, tuple[str, dict[str, dict[str, Any]]]] = {}
        self._lock = threading.Lock()
        self._stopping = threading.Event()

    def resume(self) -> None:
        """Schedules the evaluations a restart interrupted, and those of maps found due (read
        in the background)."""
        self.worker.schedule("resume", self._resume)

    def _resume(self) -> None:
        try:
            with self.sessions() as session:
                unfinished = EvaluationRepository(session).unfinished()
                following = list(session.scalars(select(Map.id).where(Map.features_auto)))
        except SQLAlchemyError as exc:
            logger.warning("self-evaluations not resumed, the database is unreachable: %s", exc)
            return
        for evaluation_id in unfinished:
            self.schedule(evaluation_id)
        # maps that grew while the server was down (``slloc import`` writes the database)
        for map_id in following:
            self.evaluate_if_due(map_id)

    def schedule(self, evaluation_id: str) -> None:
        self.worker.schedule(evaluation_id, lambda: self.run(evaluation_id))

    def run(self, evaluation_id: str) -> None:
        """Runs the evaluation to its end: ``done`` with its result, ``failed`` with the
        error, or ``cancelled`` (asked, or its map deleted)."""
        try:
            self._run(evaluation_id)
        except (EvaluationCancelled, NotFoundError):  # cancelled, or its map deleted
            logger.info("self-evaluation %s stopped", evaluation_id)
        except Exception as exc:  # a background job: whatever stops it ends it, never stuck
            logger.exception("self-evaluation %s failed", evaluation_id)
            self._end(evaluation_id, "failed", error=str(exc) or type(exc).__name__)

    def _run(self, evaluation_id: str) -> None:
        with self.sessions.begin() as session:
            repository = EvaluationRepository(session)
            row = session.get(MapEvaluation, evaluation_id)
            if row is None or row.state not in ("queued", "running"):
                return
            map_row = require_map(session, row.map_id)
            map_id, map_name = map_row.id, map_row.name
            preset = map_row.feature_preset or self.localizers.features
            options = (map_row.max_keypoints, map_row.max_side)
            request = EvaluationRequest.stored(dict(row.request))
            estimator = get_estimator(request.estimator or map_row.default_estimator)
            references: list[MapReference] = []
            keys: dict[str, tuple[str, str | None]] = {}
            for image in repository.references(map_id):
                if unusable(image) is None:
                    references.append(
                        MapReference(image.id, image.name, camera_of(image), pose_of(image))
                    )
                    keys[image.id] = (str(image.original_key), image.depth_key)
            if len(references) < 2:
                raise InvalidInputError(
                    "the map has fewer than two usable references with their originals"
                )
            configurations = list(request.configurations or ())
            sample = [
                int(i)
                for i in spread_sample(
                    centers_of(references), min(request.sample_size, len(references))
                )
            ]
            total = len(sample) * len(configurations)
            repository.set_state(evaluation_id, "running", done=0, total=total)
        logger.info(
            "self-evaluation %s of map %s: %d of %d references held out, configurations %s",
            evaluation_id,
            map_id,
            len(sample),
            len(references),
            ", ".join(configurations),
        )
        plan = HeldOutPlan(
            local_map=LOCAL_MAP,
            radius_m=request.holdout_radius_m,
            top_k=request.top_k,
            estimator=estimator,
            time_budget_s=QUERY_BUDGET_S,
        )
        originals = _BlobOriginals(self.blobs, keys)
        results: dict[str, dict[str, Any]] = {}
        votes: list[Vote] = []
        for position, name in enumerate(configurations):
            # the map's configuration at its options, the others at their defaults
            localizer = self.localizers.for_map(
                *(options if name == preset else (None, None)), name
            )
            start = time.perf_counter()
            offset = position * len(sample)
            answers = evaluate(
                localizer,
                references,
                sample,
                originals,
                plan,
                EVALUATION_DESCRIBED,  # the memory bound counts them
                self.slots,
                stopped=lambda: self._stopped(evaluation_id),
                progress=partial(self._progress, evaluation_id, offset),
                # the configuration the map serves says whether its references still match
                votes=votes if name == preset else None,
            )
            results[name] = {
                **summarize(answers),
                "duration_s": round(time.perf_counter() - start, 3),
                "references": [a.as_dict() for a in answers],
            }
        recommended = recommend(results, preset)
        stale = (
            []
            if self._stopped(evaluation_id)
            else flag_stale(
                self.sessions,
                self.blobs,
                self.features_cache,
                map_id,
                votes,
                f"self-evaluation {evaluation_id}",
            )
        )
        result = {
            "configurations": results,
            "recommended": recommended,
            "served": preset,
            "references": len(references),
            "stale": stale,
        }
        # the map that follows it moves on before the evaluation reads done: its state goes
        # from evaluating to re-extracting, never ready in between
        if self.auto is not None and not self._stopped(evaluation_id):
            self.auto.finished(map_id, recommended)
        if self._end(evaluation_id, "done", result=result):
            with self._lock:
                self.latest.pop(map_id, None)  # newest last
                self.latest[map_id] = (map_name, results)
                while len(self.latest) > LATEST_KEPT:
                    del self.latest[next(iter(self.latest))]
            self.evaluate_if_due(map_id)  # the map may have grown while it was evaluated

    def queue_if_due(self, session: Session, map_id: str) -> Callable[[], None] | None:
        """In ``session``'s transaction, stores the evaluation ``auto`` finds the map due,
        if any, and returns what schedules it once that transaction is committed (a map
        that switched its references in the same transaction then reads evaluating, never
        ready, until that evaluation ends)."""
        if self.auto is None:
            return None
        map_row = session.get(Map, map_id)
        if map_row is None or not self.auto.wanted(session, map_row):
            return None
        request = EvaluationRequest()
        try:  # each refusal comes before its write: the switch stays as it was
            row = _queue(session, map_id, request, _configurations(self.localizers, request))
        except (NotFoundError, ConflictError, InvalidInputError) as exc:
            logger.info("map %s: no automatic self-evaluation: %s", map_id, exc)
            return None
        logger.info("map %s: self-evaluation queued (features auto, the map changed)", map_id)
        return partial(self.schedule, row.id)

    def evaluate_if_due(self, map_id: str) -> None:
        """Queues an evaluation of the map when ``auto`` finds one due (the map takes its
        configuration from it and has changed enough since the last): a few reads, then the
        evaluation runs in the background."""
        if self.auto is None:
            return
        try:
            with self.sessions.begin() as session:
                start = self.queue_if_due(session, map_id)
        except SQLAlchemyError as exc:
            logger.info("map %s: no automatic self-evaluation: %s", map_id, exc)
            return
        if start is not None:
            start()

    def _stopped(self, evaluation_id: str) -> bool:
        if self._stopping.is_set():
            return True
        with self.sessions() as session:
            row = session.get(MapEvaluation, evaluation_id)
            return row is None or row.state != "running"

    def _progress(self, evaluation_id: str, offset: int, done: int) -> None:
        with self._lock:
            self.held_out += 1
        with self.sessions.begin() as session:
            row = session.get(MapEvaluation, evaluation_id)
            if row is not None and row.state == "running":
                row.done = offset + done

    def _end(self, evaluation_id: str, state: str, **values: object) -> bool:
        try:
            with self.sessions.begin() as session:
                ended = EvaluationRepository(session).set_state(evaluation_id, state, **values)
        except SQLAlchemyError as exc:
            logger.warning("self-evaluation %s: its end was not stored: %s", evaluation_id, exc)
            return False
        if ended:
            with self._lock:
                self.finished[state] = self.finished.get(state, 0) + 1
        return ended

    def shutdown(self) -> None:
        self._stopping.set()
        self.worker.shutdown()
