"""Maps: create, list, get, change, delete, reindex."""

from __future__ import annotations

from fastapi import APIRouter, Response
from sqlalchemy.orm import Session, sessionmaker

from app.api.deps import (
    AdminKey,
    BlobsDep,
    ClientKey,
    EngineConfigDep,
    EvaluatorDep,
    Limit,
    LocalizersDep,
    Offset,
    ReextractorDep,
    ReferenceCacheDep,
    SessionsDep,
    SettingsDep,
)
from app.errors import problem_responses
from app.schemas.maps import MapCreate, MapOut, MapPage, MapPatch, ReindexOut
from app.usecases import maps
from app.usecases.reextraction import change_feature_options, reextraction_progress
from app.usecases.reindex import reindex_map
from app.usecases.served_features import map_serving
from services.components import EngineConfig, Localizers
from services.errors import InvalidInputError
from services.features.configs import AUTO

router = APIRouter(prefix="/v1/maps", tags=["maps"])


def _out(
    record: maps.MapRecord,
    sessions: sessionmaker[Session],
    localizers: Localizers,
    engine: EngineConfig,
) -> MapOut:
    serving = map_serving(
        record.id,
        record.max_keypoints,
        record.max_side,
        record.described_by,
        localizers,
        engine.models_dir,
        engine.features,
        record.feature_preset,
    )
    progress = reextraction_progress(sessions, localizers, record)
    return MapOut.from_record(record, serving, engine.features, progress)


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
    localizers: LocalizersDep,
    settings: SettingsDep,
    engine: EngineConfigDep,
) -> MapOut:
    """``features`` must name a configuration the server serves (or ``auto``, the default),
    be honourable by its extractor and within the service's limits (``SLLOC_MAX_KEYPOINTS``,
    ``SLLOC_MAX_SIDE``), else 422."""
    options = body.features
    record = maps.create_map(
        sessions,
        localizers,
        body.name,
        body.description,
        body.default_estimator,
        maps.FeatureChoice(options.preset, options.max_keypoints, options.max_side),
        maps.FeatureLimits(settings.max_keypoints, settings.max_side),
        body.grow_from_queries,
        body.retire_stale,
    )
    return _out(record, sessions, localizers, engine)


@router.get(
    "",
    operation_id="list_maps",
    dependencies=[ClientKey],
    responses=problem_responses(401, 422),
)
def list_maps(
    sessions: SessionsDep,
    localizers: LocalizersDep,
    engine: EngineConfigDep,
    offset: Offset = 0,
    limit: Limit = 100,
) -> MapPage:
    records, total = maps.list_maps(sessions, offset, limit)
    items = [_out(r, sessions, localizers, engine) for r in records]
    return MapPage(items=items, total=total, offset=offset, limit=limit)


@router.get(
    "/{map_id}",
    operation_id="get_map",
    dependencies=[ClientKey],
    responses=problem_responses(401, 404),
)
def get_map(
    map_id: str, sessions: SessionsDep, localizers: LocalizersDep, engine: EngineConfigDep
) -> MapOut:
    """``feature_models`` says what the map's references were described by and whether this
    server can serve them (``servable``; else the models it lacks);
    ``references_without_original`` counts the images added before originals were kept."""
    record = maps.get_map(sessions, map_id)
    return _out(record, sessions, localizers, engine)


@router.patch(
    "/{map_id}",
    operation_id="update_map",
    dependencies=[AdminKey],
    responses=problem_responses(400, 401, 403, 404, 409, 413, 422),
)
def update_map(
    map_id: str,
    body: MapPatch,
    sessions: SessionsDep,
    localizers: LocalizersDep,
    settings: SettingsDep,
    engine: EngineConfigDep,
    reextractor: ReextractorDep,
    evaluator: EvaluatorDep,
) -> MapOut:
    """Changes the map's description, default estimator or features. A new feature
    configuration (one the server serves, else 422) or options (within
    ``SLLOC_MAX_KEYPOINTS`` and ``SLLOC_MAX_SIDE``, else 422) start describing the map's
    references anew from their originals in the background: the answer shows
    ``features.state`` re-extracting with its progress, localize keeps answering with the
    current descriptions, and the map switches to the new ones at once when every reference
    is described (references whose original cannot be read keep their old description and
    are no longer searched). 409 when the map holds references added before originals were
    kept. ``features.preset`` ``auto`` makes the map follow its self-evaluation (it keeps
    its configuration until an evaluation recommends another); a name stops following."""
    fields = body.model_fields_set
    record = maps.get_map(sessions, map_id)  # 404 before anything changes
    auto = None
    if "features" in fields and body.features is not None:
        options = body.features
        maps.FeatureLimits(settings.max_keypoints, settings.max_side).check(
            options.max_keypoints, options.max_side
        )
        auto = options.preset == AUTO if options.preset is not None else None
        preset = record.feature_preset if options.preset in (None, AUTO) else options.preset
        if auto and preset not in (None, *localizers.choices):
            preset = None  # a configuration no longer served: the server's until evaluated
        if preset is not None and preset not in localizers.choices:
            raise InvalidInputError(f"features.preset: {localizers.refusal(preset)}")
        change_feature_options(
            sessions,
            localizers,
            map_id,
            maps.FeatureChoice(preset, options.max_keypoints, options.max_side),
            reextractor,
        )
    maps.update_map(
        sessions,
        map_id,
        body.description,
        body.default_estimator,
        fields,
        auto,
        body.grow_from_queries,
        body.retire_stale,
    )
    if auto:
        evaluator.evaluate_if_due(map_id)
    return _out(maps.get_map(sessions, map_id), sessions, localizers, engine)


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
    map_id: str, sessions: SessionsDep, localizers: LocalizersDep, engine: EngineConfigDep
) -> ReindexOut:
    """Train a new VLAD retrieval vocabulary from the map's stored local descriptors and
    re-encode every reference with it (no image is re-read). Maps train one automatically
    at 16 references and again each time they have grown fourfold; this forces it."""
    reindexed = reindex_map(sessions, localizers, map_id, engine.vlad)
    return ReindexOut.from_reindexed(reindexed)
