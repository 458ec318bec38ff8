"""App factory: ``create_app()`` wires settings, database, localizer and routers."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from functools import partial
from importlib.metadata import version

from anyio import CapacityLimiter
from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi_offline import FastAPIOffline

from app.admission import Admission
from app.api.deps import localize_context
from app.api.openapi import install_openapi
from app.api.routes import captures, evaluations, geo, gpp, health, images, localize, maps
from app.ar_page import install_ar_page
from app.auth import ApiKeyGate
from app.blob_sweep import StartupSweep
from app.engine_config import engine_config, service_memory_bound, thread_plan
from app.errors import install_error_handlers
from app.limits import BodyMemory, BodySizeLimit
from app.logs import install_request_id_records
from app.metrics import RequestMetrics, ServiceMetrics
from app.metrics import router as metrics_router
from app.request_context import RequestContext
from app.settings import Settings, get_settings
from app.usecases.auto_features import AutoEvaluation
from app.usecases.captures import CaptureRunner
from app.usecases.evaluations import Evaluator
from app.usecases.growth import QueryGrowth
from app.usecases.images import train_vocabulary_if_due
from app.usecases.query_outcomes import QueryOutcomes
from app.usecases.reextraction import Reextractor
from app.viewer import install_viewer
from db.blobs import open_blob_store
from db.migrate import upgrade
from db.session import make_engine, make_session_factory
from services.components import Localizers, build_localizer
from services.localization.localizer import Localizer
from services.localization.second_opinion import DescribedCache
from services.references.cache import ReferenceFeatureCache
from services.retrieval.ann import AnnOptions
from services.retrieval.cache import RetrievalIndexCache
from services.retrieval.training import BackgroundTrainer
from services.runtime.memory import SECOND_OPINION_DESCRIBED
from services.runtime.spare_workers import SpareWorkers
from services.runtime.threads import apply_thread_plan
from services.runtime.worker_slots import WorkerSlots

logger = logging.getLogger(__name__)


def create_app(settings: Settings | None = None, localizer: Localizer | None = None) -> FastAPI:
    """Build the app. ``localizer`` may be injected (tests share one across apps)."""
    settings = settings or get_settings()
    install_request_id_records()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        engine = make_engine(settings.database_url)
        if settings.auto_migrate:
            upgrade(engine)
        app.state.engine = engine
        app.state.sessions = make_session_factory(engine)
        app.state.settings = settings
        app.state.thread_plan = plan = thread_plan(settings)
        apply_thread_plan(plan)
        # what the engine serves, resolved once: the localizer, the memory bound, health and
        # the served-features checks all read it
        app.state.engine_config = served = engine_config(settings, app.state.sessions, plan)
        app.state.localizers = localizers = Localizers(
            served, localizer or build_localizer(served), settings.parsed_evaluation_features()
        )
        app.state.ann_builder = BackgroundTrainer("retrieval index")
        app.state.retrieval_cache = RetrievalIndexCache(
            AnnOptions(settings.ann_min_references, settings.ann_nprobe),
            builder=app.state.ann_builder,
        )
        app.state.reference_cache = ReferenceFeatureCache(settings.reference_cache_mib * 2**20)
        app.state.described_cache = DescribedCache(SECOND_OPINION_DESCRIBED)
        app.state.vocabulary_trainer = BackgroundTrainer()
        app.state.memory_bound = bound = service_memory_bound(settings, served)
        # the workers compute within the memory the bound counts for them
        slots = WorkerSlots(plan.workers, bound.terms["computing"])
        app.state.admission = Admission(slots, settings.max_queued)
        # a request alone matches on every worker's core: the idle slots are lent to it
        app.state.spare_workers = SpareWorkers(slots.semaphore, plan.workers - 1)
        logger.info(
            "memory bound: %s; plus the retrieval indexes, which grow with the references "
            "(docs: deploying, Memory)",
            bound.describe(),
        )
        # the originals of reference images (db/blobs.py), reconciled with the rows
        app.state.blobs = blobs = open_blob_store(
            settings.blob_url, settings.database_url, settings.data_dir
        )
        logger.info("originals of reference images: %s", blobs.description)
        # its probe (health, readiness, /metrics): one at a time, so that a store that hangs
        # holds one thread
        app.state.blob_probe_threads = CapacityLimiter(1)
        app.state.blob_sweep = (
            StartupSweep(app.state.sessions, blobs, settings.blob_sweep_grace_s)
            if settings.blob_sweep_on_start
            else None
        )
        # maps whose feature options changed: their references described anew, resumed; a
        # map that switched trains its retrieval vocabulary and is evaluated when it grew
        # meanwhile
        train = partial(train_vocabulary_if_due, app.state.sessions, app.state.vocabulary_trainer)

        def switched(map_id: str, localizer: Localizer) -> None:
            if served.vlad:
                train(map_id, localizer)
            app.state.evaluator.evaluate_if_due(map_id)

        app.state.reextractor = Reextractor(
            app.state.sessions,
            localizers,
            blobs,
            app.state.reference_cache,
            on_switch=switched,
            slots=app.state.admission.slots,
            queue_evaluation=lambda session, map_id: app.state.evaluator.queue_if_due(
                session, map_id
            ),
        )
        app.state.reextractor.resume()
        # maps' self-evaluations; those a restart interrupted run again; maps that follow
        # theirs are evaluated as they grow and take the configuration recommended
        auto = AutoEvaluation(
            app.state.sessions,
            localizers,
            app.state.reextractor,
            settings.auto_evaluation_references,
        )
        app.state.evaluator = Evaluator(
            app.state.sessions,
            localizers,
            blobs,
            app.state.admission.slots,
            auto,
            app.state.reference_cache,
        )
        app.state.evaluator.resume()
        # capture sessions, aligned to their map and added (then the map may train its
        # vocabulary and be evaluated, as after a switch); those a restart interrupted resume
        app.state.capture_runner = CaptureRunner(localize_context(app.state), blobs, switched)
        # maps that grow from their confident queries
        app.state.query_growth = QueryGrowth(
            app.state.sessions, localizers, blobs, app.state.admission.slots, switched
        )
        app.state.capture_runner.resume()
        # where single-frame queries localize and fail (the map's coverage reads them)
        app.state.query_outcomes = QueryOutcomes(app.state.sessions)
        # health's database probe; apart from the thread pool other routes may fill
        app.state.health_threads = CapacityLimiter(2)
        if not settings.api_keys:
            logger.warning("SLLOC_API_KEYS is empty: authentication is OFF, anyone may write")
        logger.info("slloc ready: database %s", engine.url.render_as_string(hide_password=True))
        yield
        app.state.draining = True  # /readyz answers 503 from now on
        app.state.reextractor.shutdown()
        app.state.evaluator.shutdown()
        app.state.capture_runner.shutdown()
        app.state.query_growth.shutdown()
        app.state.query_outcomes.shutdown()
        app.state.vocabulary_trainer.shutdown()
        app.state.spare_workers.shutdown()
        app.state.ann_builder.shutdown()
        if app.state.blob_sweep is not None:
            app.state.blob_sweep.join(5.0)
        engine.dispose()

    # /docs and /redoc load Swagger UI and ReDoc from the service itself (no CDN, no fonts).
    app = FastAPIOffline(
        title="slloc",
        version=version("slloc"),
        summary="Structureless visual localization against a mutable database of posed images.",
        lifespan=lifespan,
    )
    # Two uploads (image, depth) plus form fields may share one request.
    memory = BodyMemory(settings.body_memory_mib * 2**20)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes, memory=memory)
    # outside the body limit: a missing or unknown key is answered before anything reads the
    # body
    routers = [
        *(m.router for m in (maps, images, captures, evaluations, geo, localize, gpp, health)),
        evaluations.coverage_router,
    ]
    routes = [route for router in routers for route in router.routes]
    app.add_middleware(ApiKeyGate, routes=routes)
    # outside the key gate: a browser's preflight carries no key (SLLOC_CORS_ORIGINS)
    if origins := settings.parsed_cors_origins():
        app.add_middleware(
            CORSMiddleware,
            allow_origins=origins,
            allow_methods=["*"],
            allow_headers=["*"],
            expose_headers=["X-Request-ID", "Retry-After"],
            max_age=600,
        )
    # around the others: every answer, their 401 and 413 included, carries the request id
    app.add_middleware(RequestContext)
    # outermost: every answer is counted under its route template
    app.state.metrics = ServiceMetrics(app.state)
    app.add_middleware(RequestMetrics, metrics=app.state.metrics, routes=routes)
    install_error_handlers(app, routes)
    for router in routers:
        app.include_router(router)
    app.include_router(metrics_router)
    app.include_router(health.probes)
    install_viewer(app)
    install_ar_page(app)
    install_openapi(app)
    return app
