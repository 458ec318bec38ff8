"""The wider retrieval: a query whose answer stays unsure after the turn search is matched
again against references spread wider apart
(``services.retrieval.thinning.WIDER_SPACING_FACTOR``), and each unsure answer keeps the more
confident of its two.

Where a map holds several passes through a place, the references retrieved first can all
come from one pass: a short baseline along one line, on which ``e5p1`` and ``local_tri_all``
disagree by decimetres and the confidence falls. A wider spread gives the estimators the
baseline back. It runs only for unsure answers: a confident one keeps its references, and a
spread kept wide for every query loses accuracy where the closest references were the right
ones (both dev sets: ``docs/benchmarks/2026-11-29-wider-retrieval.md``)."""

from __future__ import annotations

from collections.abc import Callable

from services.estimators.base import FailureReason
from services.estimators.options import RansacOptions
from services.estimators.ransac import searched_in_vain
from services.localization.answer import LocalizationResult
from services.localization.clock import OutOfTimeError, StageClock
from services.localization.stages import MatchedQuery
from services.localization.turns import better

# an answer below this confidence is matched again against a wider spread
SURE_CONFIDENCE = 0.5


def widen_unsure(
    results: list[LocalizationResult],
    upright: MatchedQuery,
    match_wider: Callable[[MatchedQuery], MatchedQuery | None],
    estimate: Callable[[int, MatchedQuery], LocalizationResult],
    clock: StageClock,
    ransac: RansacOptions,
) -> tuple[list[LocalizationResult], list[bool]]:
    """``results`` (the answers of the estimates ``estimate(i, matched)``) with each unsure
    one replaced by the better (``turns.better``) of it and its estimate on
    ``match_wider(upright)``, while the budget lasts; and, for each, whether it was estimated
    on that wider match. ``match_wider`` answers None when the wider retrieval brings no other
    reference (a small map): nothing is estimated again. ``ransac``: the options the
    estimates ran with (``sure``)."""
    again = [not sure(r, ransac) for r in results]
    untouched = [False] * len(results)
    if not any(again) or clock.deadline.expired():
        return results, untouched
    try:
        wider = match_wider(upright)
    except OutOfTimeError:
        return results, untouched
    if wider is None:
        return results, untouched
    results = [
        better(r, estimate(i, wider)) if unsure else r
        for i, (r, unsure) in enumerate(zip(results, again, strict=True))
    ]
    clock.lap("estimate", check=False)
    return results, again


def sure(result: LocalizationResult, ransac: RansacOptions) -> bool:
    """No other spread of references needs trying for this answer: it is localized with
    ``SURE_CONFIDENCE`` or more, failed for want of depth, which no reference brings, or its
    pose search drew every hypothesis ``ransac`` allows without an answer (``searched_in_vain``:
    an image of nothing in the map; no wider spread localized such a query on either
    development set)."""
    if result.reason == FailureReason.MISSING_DEPTH.value:
        return True
    if not result.localized and searched_in_vain(result.stats, ransac):
        return True
    return result.localized and result.confidence >= SURE_CONFIDENCE
