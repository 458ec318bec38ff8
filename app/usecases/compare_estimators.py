"""Localize one query with several estimators on the same matches (the evaluation's path:
the query is described, retrieved and matched once)."""

from __future__ import annotations

from collections.abc import Sequence

from sqlalchemy.orm import Session, sessionmaker

from app.usecases.localize import LocalizeRequest, engine_params, reference_store
from app.usecases.maps import require_map
from services.pipeline import LocalizationResult, Localizer
from services.retrieval.cache import RetrievalIndexCache


def localize_with_each(
    sessions: sessionmaker[Session],
    localizer: Localizer,
    map_id: str,
    request: LocalizeRequest,
    estimators: Sequence[str],
    image_bytes: bytes,
    depth_bytes: bytes | None = None,
    *,
    max_top_k: int,
    cache: RetrievalIndexCache | None = None,
) -> list[LocalizationResult]:
    """One result per name of ``estimators`` (``request.estimator`` is not used), each as
    ``localize`` with that estimator answers, from one description and matching of the query;
    an estimator that needs depth answers ``missing_depth`` when ``depth_bytes`` is None.

    Raises:
        NotFoundError: unknown map.
        InvalidInputError: the image, depth, camera or parameters are unusable.
    """
    with sessions() as session:
        map_row = require_map(session, map_id)
        localizer = localizer.for_map(map_row.max_keypoints, map_row.max_side)
        params = engine_params(request, map_row.default_estimator, max_top_k)
    store = reference_store(sessions, map_id, localizer, cache)
    return localizer.localize_each(image_bytes, params, estimators, store, depth_bytes)
