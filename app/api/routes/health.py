"""Liveness and what the service runs with."""

from __future__ import annotations

from importlib.metadata import version

from anyio import to_thread
from fastapi import APIRouter, Request
from sqlalchemy import text
from sqlalchemy.orm import Session, sessionmaker

from app.api.deps import LocalizerDep, SessionsDep
from app.schemas.health import HealthOut, ModelsOut
from services.estimators.registry import estimator_names

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
    )


def _database_up(sessions: sessionmaker[Session]) -> bool:
    try:
        with sessions() as session:
            session.execute(text("SELECT 1"))
    except Exception:
        return False
    return True
