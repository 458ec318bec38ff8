"""Localize a query image against a map."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

from sqlalchemy.orm import Session, sessionmaker

from app.usecases.maps import require_map
from app.usecases.served_features import check_servable, map_localizer
from db.blobs import BlobStore
from db.store import SqlReferenceStore
from db.vocabulary import SqlVocabularyStore
from services.components import Localizers
from services.errors import InvalidInputError
from services.estimators.options import EstimatorOptions
from services.estimators.registry import get_estimator
from services.features.configs import AUTO
from services.geometry.camera import Camera
from services.localization.answer import DEFAULT_MIN_CONFIDENCE, LocalizationResult
from services.localization.localizer import LocalizeParams, Localizer
from services.localization.query_frame import QueryFrameHints
from services.localization.second_opinion import DescribedCache, ask, merged, wants_second_opinion
from services.references.cache import ReferenceFeatureCache
from services.retrieval.cache import RetrievalIndexCache
from services.retrieval.search import PositionPrior
from services.retrieval.training import BackgroundTrainer
from services.retrieval.vlad_index import VladIndexer, searchable_vocabulary
from services.runtime.spare_workers import SpareWorkers
from services.runtime.worker_slots import WorkerSlots, holding


@dataclass(frozen=True)
class LocalizeRequest:
    """What a localize call asks for; None takes the map's or the engine's default.

    Attributes:
        camera: query intrinsics (None: the engine's default camera for the image size).
        estimator: estimator name (None: the map's default estimator).
        top_k: references to retrieve.
        prior: keep only references near a known position.
        max_error_px: inlier threshold in pixels (None: the estimator options' default).
        time_budget_s: wall-clock budget of the localization in seconds (None: the service's).
        frame: an AR client's camera rotation, gravity and rotation search.
        min_confidence: a pose less confident than this is answered ``low_confidence``.
        second_opinion: whether a query the map's configuration retrieves references for but
            does not localize is localized again by the context's second configuration.
    """

    camera: Camera | None = None
    estimator: str | None = None
    top_k: int = 10
    prior: PositionPrior | None = None
    max_error_px: float | None = None
    time_budget_s: float | None = None
    frame: QueryFrameHints = field(default_factory=QueryFrameHints)
    min_confidence: float = DEFAULT_MIN_CONFIDENCE
    second_opinion: bool = True


def engine_params(
    request: LocalizeRequest,
    default_estimator: str,
    max_top_k: int,
    max_time_budget_s: float | None = None,
) -> LocalizeParams:
    """The engine's parameters for ``request`` on a map whose default estimator is
    ``default_estimator``, with the time budget ``max_time_budget_s`` unless the request asks
    for less (None: unbounded).

    Raises:
        InvalidInputError: ``top_k`` exceeds ``max_top_k``, or ``time_budget_s`` exceeds
            ``max_time_budget_s``.
    """
    if request.top_k > max_top_k:
        raise InvalidInputError(f"top_k may be at most {max_top_k}")
    budget = max_time_budget_s
    if request.time_budget_s is not None:
        if max_time_budget_s is not None and request.time_budget_s > max_time_budget_s:
            raise InvalidInputError(f"time_budget_s may be at most {max_time_budget_s}")
        budget = request.time_budget_s
    options = EstimatorOptions()
    if request.max_error_px is not None:
        ransac = replace(options.ransac, max_error_px=request.max_error_px)
        options = replace(options, ransac=ransac)
    return LocalizeParams(
        camera=request.camera,
        estimator=get_estimator(request.estimator or default_estimator),
        top_k=request.top_k,
        prior=request.prior,
        options=options,
        time_budget_s=budget,
        frame=request.frame,
        min_confidence=request.min_confidence,
    )


@dataclass(frozen=True)
class LocalizeContext:
    """What every localize shares besides its request: the database, the engine, the
    service's limits and the state kept between requests.

    Attributes:
        sessions: the database.
        localizers: the engine, one localizer per feature configuration served (set up for
            each map by ``for_map``).
        max_top_k: the largest ``top_k`` a request may ask for.
        max_time_budget_s: the time budget, and the largest a request may ask for (None:
            unbounded).
        cache: keeps maps' retrieval indexes in memory between calls.
        vlad: retrieve by the map's VLAD vocabulary once it has one (False: the localizer's
            global descriptor).
        slots: held while the engine runs, with the request's memory (bounds concurrent
            engine work; None: unbounded).
        spare: the idle worker slots a request's matching may borrow (None: none lent).
        trainer: where a retrieval vocabulary found due is trained (None: before the search).
        features_cache: keeps the decoded features of references between calls.
        blobs: where the references' originals are, for the refinement of matches (None:
            matches are not refined).
        models_dir / features: where the server's models are and its feature configuration
            (named when a map's references need models it lacks).
        second_opinion: the configuration a query its map's own does not localize is
            localized with again (``services.localization.second_opinion``): ``auto`` (the
            first served that is not the map's), a name, or empty (none).
        described: the references described for second opinions, kept between requests
            (None: a second opinion is never asked).
    """

    sessions: sessionmaker[Session]
    localizers: Localizers
    max_top_k: int
    max_time_budget_s: float | None = None
    cache: RetrievalIndexCache | None = None
    vlad: bool = True
    slots: WorkerSlots | None = None
    spare: SpareWorkers | None = None
    trainer: BackgroundTrainer | None = None
    features_cache: ReferenceFeatureCache | None = None
    blobs: BlobStore | None = None
    models_dir: Path = Path("models")
    features: str = ""
    second_opinion: str = ""
    described: DescribedCache | None = None

    def map_engine(
        self, map_id: str, request: LocalizeRequest
    ) -> tuple[Localizer, LocalizeParams, SqlReferenceStore]:
        """The localizer of the map's feature configuration set up for its options, the
        engine's parameters for ``request`` (the estimator resolved: the map's where it names
        none) and the map's references.

        Raises:
            NotFoundError: unknown map.
            FeaturesUnavailableError: none of the map's references is described as this
                server describes queries (their models are missing here).
            InvalidInputError: ``top_k`` or ``time_budget_s`` over the limits.
        """
        with self.sessions() as session:
            map_row = require_map(session, map_id)
            check_servable(
                session,
                map_id,
                map_row.max_keypoints,
                map_row.max_side,
                self.localizers,
                self.models_dir,
                self.features,
                map_row.feature_preset,
            )
            localizer = map_localizer(self.localizers, map_row)
            params = engine_params(
                request,
                map_row.default_estimator,
                self.max_top_k,
                self.max_time_budget_s,
            )
        store = reference_store(
            self.sessions,
            map_id,
            localizer,
            self.cache,
            self.vlad,
            self.trainer,
            self.features_cache,
            self.blobs,
        )
        return localizer, params, store

    def second_localizer(self, map_id: str) -> tuple[str, Localizer] | None:
        """The configuration that gives the map's queries a second opinion, and its localizer
        at its defaults; None when there is none (turned off, or the server serves no other)."""
        if not self.second_opinion or self.described is None:
            return None
        with self.sessions() as session:
            preset = require_map(session, map_id).feature_preset or self.localizers.features
        name = second_configuration(self.localizers.choices, self.second_opinion, preset)
        return (name, self.localizers.get(name)) if name is not None else None


def second_configuration(served: Sequence[str], setting: str, preset: str) -> str | None:
    """The configuration of ``setting`` (``auto``: the first of ``served`` other than the map's
    ``preset``; a name: that one where it is served and not the map's; empty: none)."""
    if setting == AUTO:
        return next((name for name in served if name != preset), None)
    return setting if setting and setting != preset and setting in served else None


def localize(
    context: LocalizeContext,
    map_id: str,
    request: LocalizeRequest,
    image_bytes: bytes,
    depth_bytes: bytes | None = None,
) -> LocalizationResult:
    """Localize the query against the map's references. A query that cannot be localized is
    a result with ``localized`` False and a reason, not an error.

    Raises:
        NotFoundError: unknown map.
        InvalidInputError: the image, depth, camera or parameters are unusable, or the
            estimator needs depth and none was uploaded.
    """
    localizer, params, store = context.map_engine(map_id, request)
    if depth_bytes is None and params.estimator.needs_depth:
        raise InvalidInputError(
            f"depth: estimator {params.estimator.name} needs the query's depth map (the depth "
            "upload); the references need depth too"
        )
    start = time.monotonic()
    memory = localizer.upload_memory_mib(image_bytes, depth_bytes is not None, params.top_k)
    with holding(context.slots, memory):
        result = localizer.localize(image_bytes, params, store, depth_bytes, context.spare)
    if not request.second_opinion or not wants_second_opinion(result, params.options.ransac):
        return result
    second = context.second_localizer(map_id)
    if second is None or context.described is None:
        return result
    name, other = second
    if params.time_budget_s is not None:
        left = params.time_budget_s - (time.monotonic() - start)
        if left <= 0.0:
            return result
        params = replace(params, time_budget_s=left)
    references = store.load_references([r.image_id for r in result.retrieved])
    memory = other.upload_memory_mib(image_bytes, depth_bytes is not None, len(references))
    with holding(context.slots, memory):
        asked = ask(
            other,
            name,
            image_bytes,
            params,
            references,
            store.read_original,
            context.described,
            depth_bytes,
            context.spare,
        )
    if asked is None:
        return result
    return merged(result, *asked, params.min_confidence, params.options.uncertainty)


def reference_store(
    sessions: sessionmaker[Session],
    map_id: str,
    localizer: Localizer,
    cache: RetrievalIndexCache | None = None,
    vlad: bool = True,
    trainer: BackgroundTrainer | None = None,
    features_cache: ReferenceFeatureCache | None = None,
    blobs: BlobStore | None = None,
) -> SqlReferenceStore:
    """The map's references as ``localizer`` (already set up for the map) searches them: by
    the map's VLAD vocabulary once it has one (``vlad``), else by global descriptor; their
    originals in ``blobs``."""
    vocabulary = None
    if vlad:
        indexer = VladIndexer(SqlVocabularyStore(sessions, map_id, localizer.extractor.name))
        vocabulary = partial(searchable_vocabulary, indexer, trainer)
    return SqlReferenceStore(
        sessions,
        map_id,
        localizer.extractor.name,
        localizer.global_descriptor.name,
        cache,
        vocabulary,
        features_cache,
        blobs,
    )
