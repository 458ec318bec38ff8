"""FastAPI dependencies: settings, sessions, the localizer, API-key roles, uploads."""

from __future__ import annotations

from typing import Annotated, Any, TypeVar

from fastapi import Depends, Query, Request, UploadFile
from pydantic import BaseModel, ValidationError
from sqlalchemy.orm import Session, sessionmaker
from starlette.datastructures import State

from app.admission import Admission
from app.auth import RoleCheck
from app.errors import ProblemError, invalid, too_large
from app.metrics import ServiceMetrics
from app.settings import Settings
from app.usecases.captures import CaptureRunner
from app.usecases.evaluations import Evaluator
from app.usecases.growth import QueryGrowth
from app.usecases.localize import LocalizeContext
from app.usecases.query_outcomes import QueryOutcomes
from app.usecases.reextraction import Reextractor
from db.blobs import BlobStore
from services.components import EngineConfig, Localizers
from services.references.cache import ReferenceFeatureCache
from services.retrieval.training import BackgroundTrainer


async def get_settings_dep(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


async def get_engine_config(request: Request) -> EngineConfig:
    """What the engine serves (features, models, retrieval), resolved at start-up."""
    engine: EngineConfig = request.app.state.engine_config
    return engine


async def get_sessions(request: Request) -> sessionmaker[Session]:
    sessions: sessionmaker[Session] = request.app.state.sessions
    return sessions


async def get_localizers(request: Request) -> Localizers:
    """The localizers of the feature configurations served: the server's and those of
    ``SLLOC_EVALUATION_FEATURES``."""
    localizers: Localizers = request.app.state.localizers
    return localizers


async def get_reference_cache(request: Request) -> ReferenceFeatureCache:
    """Decoded reference features kept between requests (``SLLOC_REFERENCE_CACHE_MIB``)."""
    cache: ReferenceFeatureCache = request.app.state.reference_cache
    return cache


async def get_vocabulary_trainer(request: Request) -> BackgroundTrainer:
    """Trains retrieval vocabularies off the request path."""
    trainer: BackgroundTrainer = request.app.state.vocabulary_trainer
    return trainer


async def get_admission(request: Request) -> Admission:
    """Bounds the localize and add requests computing (``SLLOC_LOCALIZE_WORKERS``) and
    waiting (``SLLOC_MAX_QUEUED``)."""
    admission: Admission = request.app.state.admission
    return admission


async def get_localize_context(request: Request) -> LocalizeContext:
    """The database, engine, limits, caches and worker slots every localize shares."""
    return localize_context(request.app.state)


def localize_context(state: State) -> LocalizeContext:
    """The localize context of the app whose state is ``state`` (set up by its lifespan)."""
    settings: Settings = state.settings
    engine: EngineConfig = state.engine_config
    return LocalizeContext(
        sessions=state.sessions,
        localizers=state.localizers,
        max_top_k=settings.max_top_k,
        max_time_budget_s=settings.localize_time_budget_s,
        cache=state.retrieval_cache,
        vlad=engine.vlad,
        slots=state.admission.slots,
        spare=state.spare_workers,
        trainer=state.vocabulary_trainer,
        features_cache=state.reference_cache,
        blobs=state.blobs,
        models_dir=engine.models_dir,
        features=engine.features,
        second_opinion=settings.second_opinion,
        described=state.described_cache,
    )


async def get_evaluator(request: Request) -> Evaluator:
    """Runs maps' self-evaluations in the background."""
    evaluator: Evaluator = request.app.state.evaluator
    return evaluator


async def get_capture_runner(request: Request) -> CaptureRunner:
    """Aligns submitted capture sessions and adds their frames in the background."""
    runner: CaptureRunner = request.app.state.capture_runner
    return runner


async def get_query_outcomes(request: Request) -> QueryOutcomes:
    """Counts where single-frame queries localize and fail."""
    outcomes: QueryOutcomes = request.app.state.query_outcomes
    return outcomes


async def get_query_growth(request: Request) -> QueryGrowth:
    """Adds confident queries to maps that grow from them."""
    growth: QueryGrowth = request.app.state.query_growth
    return growth


async def get_reextractor(request: Request) -> Reextractor:
    """Describes the references of maps whose feature options changed anew."""
    reextractor: Reextractor = request.app.state.reextractor
    return reextractor


async def get_blobs(request: Request) -> BlobStore:
    """Where the originals of reference images are kept (``SLLOC_BLOB_URL``)."""
    blobs: BlobStore = request.app.state.blobs
    return blobs


async def get_metrics(request: Request) -> ServiceMetrics:
    metrics: ServiceMetrics = request.app.state.metrics
    return metrics


SettingsDep = Annotated[Settings, Depends(get_settings_dep)]
EngineConfigDep = Annotated[EngineConfig, Depends(get_engine_config)]
SessionsDep = Annotated[sessionmaker[Session], Depends(get_sessions)]
LocalizersDep = Annotated[Localizers, Depends(get_localizers)]
ReferenceCacheDep = Annotated[ReferenceFeatureCache, Depends(get_reference_cache)]
AdmissionDep = Annotated[Admission, Depends(get_admission)]
TrainerDep = Annotated[BackgroundTrainer, Depends(get_vocabulary_trainer)]
MetricsDep = Annotated[ServiceMetrics, Depends(get_metrics)]
BlobsDep = Annotated[BlobStore, Depends(get_blobs)]
ReextractorDep = Annotated[Reextractor, Depends(get_reextractor)]
EvaluatorDep = Annotated[Evaluator, Depends(get_evaluator)]
CaptureRunnerDep = Annotated[CaptureRunner, Depends(get_capture_runner)]
QueryGrowthDep = Annotated[QueryGrowth, Depends(get_query_growth)]
QueryOutcomesDep = Annotated[QueryOutcomes, Depends(get_query_outcomes)]
LocalizeContextDep = Annotated[LocalizeContext, Depends(get_localize_context)]

# paging: bounded so that every value fits the databases' integer types (else 422)
MAX_OFFSET = 2**31 - 1
Offset = Annotated[int, Query(ge=0, le=MAX_OFFSET, description="Items to skip")]
Limit = Annotated[int, Query(ge=1, le=1000, description="Items per page")]


AdminKey = Depends(RoleCheck(("admin",)))
ClientKey = Depends(RoleCheck(("admin", "client")))


def read_upload(upload: UploadFile, limit: int, field: str) -> bytes:
    """Read an uploaded file, refusing more than ``limit`` bytes."""
    data = upload.file.read(limit + 1)
    if len(data) > limit:
        raise too_large(f"{field} is larger than the {limit}-byte limit")
    if not data:
        raise ProblemError(422, "invalid-input", "Invalid input", f"{field} is empty")
    return data


def read_uploads(parts: list[UploadFile], limit: int, field: str) -> list[bytes]:
    """Read every part of a repeated upload field, refusing more than ``limit`` bytes in all
    (the request body limit bounds what is read before the sum is checked)."""
    out = [read_upload(part, limit, field) for part in parts]
    total = sum(len(data) for data in out)
    if total > limit:
        raise too_large(
            f"the {len(out)} {field} parts have {total} bytes together; the limit is {limit}"
        )
    return out


ModelT = TypeVar("ModelT", bound=BaseModel)


def json_form_schema(model: type[BaseModel]) -> dict[str, Any]:
    """OpenAPI keywords of a form field holding ``model`` as a JSON string; ``app.api.openapi``
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
