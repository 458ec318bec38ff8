"""Liveness and what the service runs with."""

from __future__ import annotations

import time
from importlib.metadata import version

from anyio import move_on_after, to_thread
from fastapi import APIRouter, Request, Response
from sqlalchemy import text
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker
from starlette.datastructures import State

from app.api.deps import LocalizersDep, SessionsDep
from app.blob_probe import blob_probe_ready, blob_store_ok
from app.schemas.health import HealthOut, ModelsOut, RuntimeOut, UnservableMapOut
from app.usecases.served_features import MapLocalizer, UnservableMap, unservable_maps
from db.session import sqlite_not_writable
from services.components import EngineConfig
from services.estimators.registry import estimator_names
from services.references.cache import ReferenceFeatureCache
from services.retrieval.cache import RetrievalIndexCache
from services.runtime.memory import MemoryBound
from services.runtime.threads import ThreadPlan

router = APIRouter(prefix="/v1", tags=["health"])
# Kubernetes-style probes at the root, without an API key: outside the documented API
probes = APIRouter(include_in_schema=False)
# seconds /readyz waits for the database before it answers not ready
READY_DATABASE_TIMEOUT_S = 2.0
# the unservable maps health lists, and how long their survey is reused (it reads every
# reference's models)
UNSERVABLE_LISTED = 20
UNSERVABLE_TTL_S = 15.0


@router.head("/health", include_in_schema=False)
async def health_head() -> Response:
    """HEAD of /v1/health: the process answers (a load balancer's check)."""
    return Response(status_code=200)


@probes.api_route("/livez", methods=["GET", "HEAD"])
async def livez() -> Response:
    """Liveness: the process answers on its event loop. Touches nothing else (no database),
    so that a database outage never gets the service restarted."""
    return Response("ok\n", media_type="text/plain")


@probes.api_route("/readyz", methods=["GET", "HEAD"])
async def readyz(request: Request) -> Response:
    """Readiness: the database answers within READY_DATABASE_TIMEOUT_S, the models are
    loaded and the service is not draining; else 503 naming what is not ready. A SQLite
    database whose file or folder is read-only, and a blob store that cannot take writes,
    leave it ready (reads and localize are served) and are named degraded."""
    state = request.app.state
    problems = []
    if getattr(state, "draining", False):
        problems.append("draining: shutting down")
    if getattr(state, "localizers", None) is None:
        problems.append("models: not loaded")
    sessions = getattr(state, "sessions", None)
    up = False
    if sessions is not None:
        with move_on_after(READY_DATABASE_TIMEOUT_S):
            up = await to_thread.run_sync(
                _database_up, sessions, limiter=state.health_threads, abandon_on_cancel=True
            )
    if not up:
        problems.append(f"database: unreachable within {READY_DATABASE_TIMEOUT_S:g} s")
    if problems:
        return Response(
            "not ready: " + "; ".join(problems) + "\n",
            status_code=503,
            media_type="text/plain",
            headers={"Retry-After": "5"},
        )
    # reads are still served: ready, and says what is degraded
    degraded = []
    engine = getattr(state, "engine", None)
    if engine is not None and sqlite_not_writable(engine) is not None:
        degraded.append(
            "database: not writable (its file or folder is read-only); writes answer 503"
        )
    if blob_probe_ready(state) and not await blob_store_ok(state):
        degraded.append("blob store: unavailable; adds answer 503")
    if degraded:
        return Response("ok; degraded: " + "; ".join(degraded) + "\n", media_type="text/plain")
    return Response("ok\n", media_type="text/plain")


@router.get("/health", operation_id="health")
async def health(request: Request, sessions: SessionsDep, localizers: LocalizersDep) -> HealthOut:
    """No API key needed. ``status`` is ``ok``, or ``degraded`` when the database is down,
    some map cannot be served or the blob store cannot take writes. Never waits behind other
    requests: the probes run on threads of their own."""
    state = request.app.state
    up = await to_thread.run_sync(_database_up, sessions, limiter=state.health_threads)
    count, unservable = (
        await to_thread.run_sync(_unservable, state, localizers, limiter=state.health_threads)
        if up
        else (0, [])
    )
    blobs_ok = await blob_store_ok(state)
    return HealthOut(
        status="ok" if up and not count and blobs_ok else "degraded",
        blob_store="ok" if blobs_ok else "unavailable",
        unservable_map_count=count,
        unservable_maps=[
            UnservableMapOut(
                id=m.id,
                name=m.name,
                image_count=m.image_count,
                described_by=sorted({g.feature_model for g in m.serving.described_by}),
                missing_models=list(m.serving.missing_models),
                detail=m.serving.detail,
            )
            for m in unservable
        ],
        version=version("slloc"),
        models=ModelsOut(
            features=localizers.served.extractor.name,
            matcher=localizers.served.matcher.name,
            global_descriptor=localizers.served.global_descriptor.name,
            feature_configurations=list(localizers.choices),
            estimators=estimator_names(),
        ),
        runtime=_runtime(request.app.state),
    )


def _runtime(state: State) -> RuntimeOut:
    plan: ThreadPlan = state.thread_plan
    cache: ReferenceFeatureCache = state.reference_cache
    retrieval: RetrievalIndexCache = state.retrieval_cache
    bound: MemoryBound = state.memory_bound.with_retrieval_index(retrieval.size().nbytes)
    stats = cache.stats()
    return RuntimeOut(
        cores=plan.cores,
        localize_workers=plan.workers,
        threads_per_worker=plan.threads_per_worker,
        idle_workers_lent=state.spare_workers.most,
        reference_cache_mib=stats.max_bytes / 2**20,
        reference_cache_used_mib=round(stats.bytes / 2**20, 3),
        memory_bound_mib=round(bound.total_mib, 1),
        memory_terms_mib={**bound.terms, "retrieval_index": round(bound.retrieval_index_mib, 3)},
        computing_memory_held_mib=round(state.admission.slots.held_mib, 1),
    )


def _unservable(state: State, localizer: MapLocalizer) -> tuple[int, list[UnservableMap]]:
    """The maps this server cannot serve, surveyed at most every UNSERVABLE_TTL_S seconds
    (an unreadable database: none)."""
    cached: tuple[float, int, list[UnservableMap]] | None = getattr(
        state, "unservable_survey", None
    )
    now = time.monotonic()
    if cached is not None and now - cached[0] < UNSERVABLE_TTL_S:
        return cached[1], cached[2]
    engine: EngineConfig = state.engine_config
    try:
        with state.sessions() as session:
            count, found = unservable_maps(
                session, localizer, engine.models_dir, engine.features, UNSERVABLE_LISTED
            )
    except SQLAlchemyError:
        return 0, []
    state.unservable_survey = (now, count, found)
    return count, found


def _database_up(sessions: sessionmaker[Session]) -> bool:
    try:
        with sessions() as session:
            session.execute(text("SELECT 1"))
    except Exception:
        return False
    return True
