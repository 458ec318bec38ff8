"""Liveness and what the service runs with."""

from __future__ import annotations

from importlib.metadata import version

from fastapi import APIRouter
from sqlalchemy import text

from app.api.deps import LocalizerDep, SessionsDep
from app.schemas.health import HealthOut, ModelsOut
from services.estimators.registry import estimator_names

router = APIRouter(prefix="/v1", tags=["health"])


@router.get("/health", operation_id="health")
def health(sessions: SessionsDep, localizer: LocalizerDep) -> HealthOut:
    """No API key needed. ``status`` is ``ok``, or ``degraded`` when the database is down."""
    try:
        with sessions() as session:
            session.execute(text("SELECT 1"))
        status = "ok"
    except Exception:
        status = "degraded"
    return HealthOut(
        status=status,
        version=version("slloc"),
        models=ModelsOut(
            features=localizer.extractor.name,
            matcher=localizer.matcher.name,
            global_descriptor=localizer.global_descriptor.name,
            estimators=estimator_names(),
        ),
    )
