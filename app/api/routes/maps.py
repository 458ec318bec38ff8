"""Maps: create, list, get, delete, reindex."""

from __future__ import annotations

from fastapi import APIRouter, Response

from app.api.deps import (
    AdminKey,
    ClientKey,
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

router = APIRouter(prefix="/v1/maps", tags=["maps"])


@router.post(
    "",
    status_code=201,
    operation_id="create_map",
    dependencies=[AdminKey],
    responses=problem_responses(400, 401, 403, 409, 413, 422),
)
def create_map(
    body: MapCreate, sessions: SessionsDep, localizer: LocalizerDep, settings: SettingsDep
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
    return MapOut.from_record(record)


@router.get(
    "",
    operation_id="list_maps",
    dependencies=[ClientKey],
    responses=problem_responses(401, 422),
)
def list_maps(
    sessions: SessionsDep,
    offset: Offset = 0,
    limit: Limit = 100,
) -> MapPage:
    records, total = maps.list_maps(sessions, offset, limit)
    items = [MapOut.from_record(record) for record in records]
    return MapPage(items=items, total=total, offset=offset, limit=limit)


@router.get(
    "/{map_id}",
    operation_id="get_map",
    dependencies=[ClientKey],
    responses=problem_responses(401, 404),
)
def get_map(map_id: str, sessions: SessionsDep) -> MapOut:
    return MapOut.from_record(maps.get_map(sessions, map_id))


@router.delete(
    "/{map_id}",
    status_code=204,
    operation_id="delete_map",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404),
)
def delete_map(map_id: str, sessions: SessionsDep, features_cache: ReferenceCacheDep) -> Response:
    maps.delete_map(sessions, map_id, features_cache)
    return Response(status_code=204)


@router.post(
    "/{map_id}/reindex",
    operation_id="reindex_map",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404, 409),
)
def reindex(
    map_id: str, sessions: SessionsDep, localizer: LocalizerDep, settings: SettingsDep
) -> ReindexOut:
    """Train a new VLAD retrieval vocabulary from the map's stored local descriptors and
    re-encode every reference with it (no image is re-read). Maps train one automatically
    at 16 references and again each time they have grown fourfold; this forces it."""
    reindexed = reindex_map(sessions, localizer, map_id, settings.global_model is None)
    return ReindexOut.from_reindexed(reindexed)
