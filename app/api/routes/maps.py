"""Maps: create, list, get, delete, reindex."""

from __future__ import annotations

from fastapi import APIRouter, Response

from app.api.deps import (
    AdminKey,
    BlobsDep,
    ClientKey,
    EngineConfigDep,
    Limit,
    LocalizerDep,
    Offset,
    ReferenceCacheDep,
    SessionsDep,
    SettingsDep,
)
from app.errors import problem_responses
from app.schemas.maps import MapCreate, MapOut, MapPage, ReindexOut
from app.usecases import maps
from app.usecases.reindex import reindex_map
from app.usecases.served_features import MapLocalizer, MapServing, map_serving
from services.components import EngineConfig

router = APIRouter(prefix="/v1/maps", tags=["maps"])


def _serving(record: maps.MapRecord, localizer: MapLocalizer, engine: EngineConfig) -> MapServing:
    return map_serving(
        record.id,
        record.max_keypoints,
        record.max_side,
        record.described_by,
        localizer,
        engine.models_dir,
        engine.features,
    )


@router.post(
    "",
    status_code=201,
    operation_id="create_map",
    dependencies=[AdminKey],
    responses=problem_responses(400, 401, 403, 409, 413, 422),
)
def create_map(
    body: MapCreate,
    sessions: SessionsDep,
    localizer: LocalizerDep,
    settings: SettingsDep,
    engine: EngineConfigDep,
) -> MapOut:
    """``features`` must be honourable by the service's extractor and within the service's
    limits (``SLLOC_MAX_KEYPOINTS``, ``SLLOC_MAX_SIDE``), else 422."""
    record = maps.create_map(
        sessions,
        localizer,
        body.name,
        body.description,
        body.default_estimator,
        body.features.max_keypoints,
        body.features.max_side,
        maps.FeatureLimits(settings.max_keypoints, settings.max_side),
    )
    return MapOut.from_record(record, _serving(record, localizer, engine))


@router.get(
    "",
    operation_id="list_maps",
    dependencies=[ClientKey],
    responses=problem_responses(401, 422),
)
def list_maps(
    sessions: SessionsDep,
    localizer: LocalizerDep,
    engine: EngineConfigDep,
    offset: Offset = 0,
    limit: Limit = 100,
) -> MapPage:
    records, total = maps.list_maps(sessions, offset, limit)
    items = [MapOut.from_record(r, _serving(r, localizer, engine)) for r in records]
    return MapPage(items=items, total=total, offset=offset, limit=limit)


@router.get(
    "/{map_id}",
    operation_id="get_map",
    dependencies=[ClientKey],
    responses=problem_responses(401, 404),
)
def get_map(
    map_id: str, sessions: SessionsDep, localizer: LocalizerDep, engine: EngineConfigDep
) -> MapOut:
    """``feature_models`` says what the map's references were described by and whether this
    server can serve them (``servable``; else the models it lacks);
    ``references_without_original`` counts the images added before originals were kept."""
    record = maps.get_map(sessions, map_id)
    return MapOut.from_record(record, _serving(record, localizer, engine))


@router.delete(
    "/{map_id}",
    status_code=204,
    operation_id="delete_map",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404),
)
def delete_map(
    map_id: str, sessions: SessionsDep, features_cache: ReferenceCacheDep, blobs: BlobsDep
) -> Response:
    """Deletes the map, its images and their features, then their originals."""
    maps.delete_map(sessions, map_id, features_cache, blobs)
    return Response(status_code=204)


@router.post(
    "/{map_id}/reindex",
    operation_id="reindex_map",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404, 409),
)
def reindex(
    map_id: str, sessions: SessionsDep, localizer: LocalizerDep, engine: EngineConfigDep
) -> ReindexOut:
    """Train a new VLAD retrieval vocabulary from the map's stored local descriptors and
    re-encode every reference with it (no image is re-read). Maps train one automatically
    at 16 references and again each time they have grown fourfold; this forces it."""
    reindexed = reindex_map(sessions, localizer, map_id, engine.vlad)
    return ReindexOut.from_reindexed(reindexed)
