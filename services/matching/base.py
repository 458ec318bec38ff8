"""The matcher contract every backend fulfils."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

from services.features.base import LocalFeatures
from services.types import IntArray


class Matcher(Protocol):
    name: str

    def match(self, query: LocalFeatures, reference: LocalFeatures) -> IntArray:
        """(M, 2) index pairs ``[query_index, reference_index]`` of matched keypoints."""
        ...

    def match_many(
        self, query: LocalFeatures, references: Sequence[LocalFeatures]
    ) -> list[IntArray]:
        """``match(query, r)`` for every reference, in order; backends may share work."""
        ...
