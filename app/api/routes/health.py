"""Liveness and what the service runs with."""

from __future__ import annotations

from importlib.metadata import version

from anyio import to_thread
from fastapi import APIRouter, Request
from sqlalchemy import text
from sqlalchemy.orm import Session, sessionmaker
from starlette.datastructures import State

from app.api.deps import LocalizerDep, SessionsDep
from app.schemas.health import HealthOut, ModelsOut, RuntimeOut
from services.estimators.registry import estimator_names
from services.reference_cache import ReferenceFeatureCache
from services.retrieval.cache import RetrievalIndexCache
from services.runtime.memory import MemoryBound
from services.runtime.threads import ThreadPlan

router = APIRouter(prefix="/v1", tags=["health"])


@router.get("/health", operation_id="health")
async def health(request: Request, sessions: SessionsDep, localizer: LocalizerDep) -> HealthOut:
    """No API key needed. ``status`` is ``ok``, or ``degraded`` when the database is down.
    Never waits behind other requests: the database probe runs on threads of its own."""
    up = await to_thread.run_sync(_database_up, sessions, limiter=request.app.state.health_threads)
    return HealthOut(
        status="ok" if up else "degraded",
        version=version("slloc"),
        models=ModelsOut(
            features=localizer.extractor.name,
            matcher=localizer.matcher.name,
            global_descriptor=localizer.global_descriptor.name,
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
    )


def _database_up(sessions: sessionmaker[Session]) -> bool:
    try:
        with sessions() as session:
            session.execute(text("SELECT 1"))
    except Exception:
        return False
    return True
