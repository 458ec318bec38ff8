"""FastAPI dependencies: settings, sessions, the localizer, API-key roles, uploads."""

from __future__ import annotations

import hmac
import threading
from typing import Annotated, Any, TypeVar

from fastapi import Depends, Query, Request, Security, UploadFile
from fastapi.security import APIKeyHeader
from pydantic import BaseModel, ValidationError
from sqlalchemy.orm import Session, sessionmaker

from app.errors import ProblemError, invalid, too_large
from app.settings import Role, Settings
from services.pipeline import Localizer
from services.retrieval.cache import RetrievalIndexCache
from services.retrieval.training import BackgroundTrainer

_api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False)


def get_settings_dep(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


def get_sessions(request: Request) -> sessionmaker[Session]:
    sessions: sessionmaker[Session] = request.app.state.sessions
    return sessions


def get_localizer(request: Request) -> Localizer:
    localizer: Localizer = request.app.state.localizer
    return localizer


def get_retrieval_cache(request: Request) -> RetrievalIndexCache:
    cache: RetrievalIndexCache = request.app.state.retrieval_cache
    return cache


def get_vocabulary_trainer(request: Request) -> BackgroundTrainer:
    """Trains retrieval vocabularies off the request path."""
    trainer: BackgroundTrainer = request.app.state.vocabulary_trainer
    return trainer


def get_localize_slots(request: Request) -> threading.BoundedSemaphore:
    """Held while the engine localizes (``SLLOC_LOCALIZE_WORKERS`` at once)."""
    slots: threading.BoundedSemaphore = request.app.state.localize_slots
    return slots


SettingsDep = Annotated[Settings, Depends(get_settings_dep)]
SessionsDep = Annotated[sessionmaker[Session], Depends(get_sessions)]
LocalizerDep = Annotated[Localizer, Depends(get_localizer)]
RetrievalCacheDep = Annotated[RetrievalIndexCache, Depends(get_retrieval_cache)]
LocalizeSlotsDep = Annotated[threading.BoundedSemaphore, Depends(get_localize_slots)]
TrainerDep = Annotated[BackgroundTrainer, Depends(get_vocabulary_trainer)]

# paging: bounded so that every value fits the databases' integer types (else 422)
MAX_OFFSET = 2**31 - 1
Offset = Annotated[int, Query(ge=0, le=MAX_OFFSET, description="Items to skip")]
Limit = Annotated[int, Query(ge=1, le=1000, description="Items per page")]


def _role_of(settings: Settings, key: str | None) -> Role | None:
    if key is None:
        return None
    for candidate in settings.parsed_api_keys():
        if hmac.compare_digest(candidate.key.get_secret_value().encode(), key.encode()):
            return candidate.role
    return None


def _require(allowed: tuple[Role, ...]):  # type: ignore[no-untyped-def]
    def check(settings: SettingsDep, key: Annotated[str | None, Security(_api_key_header)]) -> None:
        if not settings.api_keys:
            return  # auth is off; the app logged a warning at start-up
        role = _role_of(settings, key)
        if role is None:
            raise ProblemError(401, "unauthorized", "Unauthorized", "missing or unknown X-API-Key")
        if role not in allowed:
            raise ProblemError(
                403, "forbidden", "Forbidden", f"this needs the {' or '.join(allowed)} role"
            )

    return check


AdminKey = Depends(_require(("admin",)))
ClientKey = Depends(_require(("admin", "client")))


def read_upload(upload: UploadFile, limit: int, field: str) -> bytes:
    """Read an uploaded file, refusing more than ``limit`` bytes."""
    data = upload.file.read(limit + 1)
    if len(data) > limit:
        raise too_large(f"{field} is larger than the {limit}-byte limit")
    if not data:
        raise ProblemError(422, "invalid-input", "Invalid input", f"{field} is empty")
    return data


ModelT = TypeVar("ModelT", bound=BaseModel)


def json_form_schema(model: type[BaseModel]) -> dict[str, Any]:
    """OpenAPI keywords of a form field holding ``model`` as a JSON string; ``app.openapi``
    publishes the model's schema in the components."""
    return {
        "contentMediaType": "application/json",
        "contentSchema": {"$ref": f"#/components/schemas/{model.__name__}"},
    }


def parse_json_form(model: type[ModelT], raw: str, field: str) -> ModelT:
    """Validate a JSON string sent as a multipart form field; errors name the field."""
    try:
        return model.model_validate_json(raw)
    except ValidationError as exc:
        errors = [
            {"loc": [field, *e["loc"]], "msg": e["msg"], "type": e["type"]} for e in exc.errors()
        ]
        detail = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors)
        raise invalid(detail, errors) from None
