"""The matcher contract every backend fulfils."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol

from services.features.base import LocalFeatures
from services.runtime.spare_workers import Spread
from services.types import IntArray


class Matcher(Protocol):
    name: str

    def match(self, query: LocalFeatures, reference: LocalFeatures) -> IntArray:
        """(M, 2) index pairs ``[query_index, reference_index]`` of matched keypoints."""
        ...

    def match_many(
        self,
        query: LocalFeatures,
        references: Sequence[LocalFeatures],
        stop: Callable[[], bool] | None = None,
        spread: Spread | None = None,
    ) -> list[IntArray]:
        """``match(query, r)`` for every reference, in order; backends may share work.
        ``stop`` is asked before each reference: once it answers True the rest is skipped
        (the list may then be shorter, or hold first-pass matches only). ``spread``: how
        work that is independent per reference may run on several threads."""
        ...


def match_each(
    match: Callable[[LocalFeatures, LocalFeatures], IntArray],
    query: LocalFeatures,
    references: Sequence[LocalFeatures],
    stop: Callable[[], bool] | None = None,
    spread: Spread | None = None,
) -> list[IntArray]:
    """``match(query, r)`` for the references in order, until ``stop`` answers True; through
    ``spread`` when given."""

    def run(run_references: Sequence[LocalFeatures]) -> list[IntArray]:
        out = []
        for reference in run_references:
            if stop is not None and stop():
                break
            out.append(match(query, reference))
        return out

    return spread(run, references) if spread is not None else run(references)
