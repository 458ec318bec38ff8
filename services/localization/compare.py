"""Several estimators on the same matches (the evaluation's path): the query is decoded,
described, retrieved and matched once, through the same stages as ``Localizer.localize``."""

from __future__ import annotations

import time
from collections.abc import Sequence

from services.estimators.base import PoseEstimator
from services.localization.answer import LocalizationResult, out_of_time
from services.localization.clock import OutOfTimeError, StageClock
from services.localization.localizer import LocalizeParams, Localizer
from services.localization.stages import MatchedQuery
from services.localization.turns import search_turns, searched_answer
from services.localization.widen import widen_unsure
from services.references.store import ReferenceStore
from services.runtime.spare_workers import SpareWorkers


def localize_each(
    localizer: Localizer,
    image_bytes: bytes,
    params: LocalizeParams,
    estimators: Sequence[PoseEstimator],
    store: ReferenceStore,
    depth_bytes: bytes | None = None,
    spare: SpareWorkers | None = None,
) -> list[LocalizationResult]:
    """One result per estimator of ``estimators`` (``params.estimator`` is not used), as
    ``localizer.localize`` with that estimator answers, from one description and matching of
    the query. Each result has the shared stage timings and its own ``estimate`` time
    (``total`` leaves the other estimators out), and each estimator gets what is left of the
    time budget after matching. The turn search (``services.localization.turns``) and the wider
    retrieval (``services.localization.widen``) go on for the estimators without a settled
    answer; past one attempt, every result has the shared stages summed over the attempts and
    its own estimation time summed over its own."""
    clock = StageClock(params.time_budget_s)
    try:
        query, first = localizer.start(image_bytes, params, store, depth_bytes, spare, clock)
    except OutOfTimeError:
        timings = clock.finish()
        return [out_of_time(estimator.name, timings) for estimator in estimators]
    own_ms = [0.0] * len(estimators)  # each estimator's own estimation time, all turns

    def estimate(index: int, matched: MatchedQuery) -> LocalizationResult:
        start = time.perf_counter()
        result = localizer.estimate(matched, query, params, estimators[index], clock, spare)
        own_ms[index] += (time.perf_counter() - start) * 1000.0
        return result

    results, attempts, upright = search_turns(
        query.frame.turns,
        first,
        lambda turn: localizer.match(query, turn, params, store, clock, spare),
        estimate,
        len(estimators),
        clock,
    )
    results, widened = widen_unsure(
        results,
        upright,
        lambda matched: localizer.match_wider(query, matched, params, store, clock, spare),
        estimate,
        clock,
        params.options.ransac,
    )
    summed = clock.finish() if attempts > 1 or any(widened) else None
    return [
        searched_answer(
            result,
            attempts,
            wider,
            query.frame.adaptation,
            own_timings(summed, own) if summed else result.timings_ms,
            params.min_confidence,
        )
        for result, own, wider in zip(results, own_ms, widened, strict=True)
    ]


def own_timings(summed: dict[str, float], own_estimate_ms: float) -> dict[str, float]:
    """One estimator's stage timings over several turns: the shared stages as ``summed``
    (all turns), its own estimation time instead of every estimator's, and ``total`` with
    the other estimators' time taken out."""
    others_ms = summed["estimate"] - own_estimate_ms
    return {**summed, "estimate": own_estimate_ms, "total": summed["total"] - others_ms}
