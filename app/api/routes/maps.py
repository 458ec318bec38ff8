"""Maps: create, list, get, delete, reindex."""

from __future__ import annotations

from fastapi import APIRouter, Query, Response
from fastapi.concurrency import run_in_threadpool
from sqlalchemy.exc import IntegrityError

from app.api.deps import AdminKey, ClientKey, LocalizerDep, SessionsDep, SettingsDep
from app.errors import conflict, not_found, problem_responses
from app.operations import reindex_map
from app.schemas.maps import FeatureOptions, MapCreate, MapOut, MapPage, ReindexOut
from db.models import Map
from db.repositories.maps import MapRepository

router = APIRouter(prefix="/v1/maps", tags=["maps"])


def _out(row: Map, image_count: int) -> MapOut:
    return MapOut(
        id=row.id,
        name=row.name,
        description=row.description,
        default_estimator=row.default_estimator,
        features=FeatureOptions(max_keypoints=row.max_keypoints, max_side=row.max_side),
        image_count=image_count,
        created_at=row.created_at,
    )


@router.post(
    "",
    status_code=201,
    operation_id="create_map",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 409, 422),
)
def create_map(body: MapCreate, sessions: SessionsDep, localizer: LocalizerDep) -> MapOut:
    """``features`` must be honourable by the service's extractor (else 422)."""
    options = body.features
    localizer.for_map(options.max_keypoints, options.max_side)
    try:
        with sessions.begin() as session:
            repo = MapRepository(session)
            if repo.get_by_name(body.name) is not None:
                raise conflict(f"a map named {body.name!r} exists")
            row = repo.create(
                body.name,
                body.description,
                body.default_estimator,
                options.max_keypoints,
                options.max_side,
            )
            return _out(row, 0)
    except IntegrityError as exc:
        raise conflict(f"a map named {body.name!r} exists") from exc


@router.get(
    "",
    operation_id="list_maps",
    dependencies=[ClientKey],
    responses=problem_responses(401, 422),
)
def list_maps(
    sessions: SessionsDep,
    offset: int = Query(0, ge=0),
    limit: int = Query(100, ge=1, le=1000),
) -> MapPage:
    with sessions() as session:
        repo = MapRepository(session)
        rows, total = repo.page(offset, limit)
        counts = repo.image_counts([row.id for row in rows])
        items = [_out(row, counts.get(row.id, 0)) for row in rows]
    return MapPage(items=items, total=total, offset=offset, limit=limit)


@router.get(
    "/{map_id}",
    operation_id="get_map",
    dependencies=[ClientKey],
    responses=problem_responses(401, 404),
)
def get_map(map_id: str, sessions: SessionsDep) -> MapOut:
    with sessions() as session:
        repo = MapRepository(session)
        row = repo.get(map_id)
        if row is None:
            raise not_found("map", map_id)
        return _out(row, repo.image_counts([map_id]).get(map_id, 0))


@router.delete(
    "/{map_id}",
    status_code=204,
    operation_id="delete_map",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404),
)
def delete_map(map_id: str, sessions: SessionsDep) -> Response:
    with sessions.begin() as session:
        if not MapRepository(session).delete(map_id):
            raise not_found("map", map_id)
    return Response(status_code=204)


@router.post(
    "/{map_id}/reindex",
    operation_id="reindex_map",
    dependencies=[AdminKey],
    responses=problem_responses(401, 403, 404, 409),
)
async def reindex(
    map_id: str, sessions: SessionsDep, localizer: LocalizerDep, settings: SettingsDep
) -> ReindexOut:
    """Train a new VLAD retrieval vocabulary from the map's stored local descriptors and
    re-encode every reference with it (no image is re-read). Maps train one automatically
    at 16 references and again each time they have grown fourfold; this forces it."""
    return await run_in_threadpool(
        reindex_map, sessions, localizer, map_id, settings.global_model is None
    )
