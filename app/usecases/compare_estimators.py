"""Localize one query with several estimators on the same matches (the evaluation's path:
the query is described, retrieved and matched once)."""

from __future__ import annotations

from collections.abc import Sequence

from app.usecases.localize import LocalizeContext, LocalizeRequest
from services.estimators.registry import get_estimator
from services.localization.answer import LocalizationResult
from services.localization.compare import localize_each
from services.runtime.worker_slots import holding


def localize_with_each(
    context: LocalizeContext,
    map_id: str,
    request: LocalizeRequest,
    estimators: Sequence[str],
    image_bytes: bytes,
    depth_bytes: bytes | None = None,
) -> list[LocalizationResult]:
    """One result per name of ``estimators`` (``request.estimator`` is not used), each as
    ``localize`` with that estimator answers, from one description and matching of the query;
    an estimator that needs depth answers ``missing_depth`` when ``depth_bytes`` is None.

    Raises:
        NotFoundError: unknown map.
        InvalidInputError: the image, depth, camera or parameters are unusable.
    """
    localizer, params, store = context.map_engine(map_id, request)
    memory = localizer.upload_memory_mib(image_bytes, depth_bytes is not None, params.top_k)
    with holding(context.slots, memory):
        return localize_each(
            localizer,
            image_bytes,
            params,
            [get_estimator(name) for name in estimators],
            store,
            depth_bytes,
            context.spare,
        )
