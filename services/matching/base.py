"""The matcher contract every backend fulfils."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from services.features.base import LocalFeatures


class Matcher(Protocol):
    name: str

    def match(self, query: LocalFeatures, reference: LocalFeatures) -> NDArray[np.int64]:
        """(M, 2) index pairs ``[query_index, reference_index]`` of matched keypoints."""
        ...

    def match_many(
        self, query: LocalFeatures, references: Sequence[LocalFeatures]
    ) -> list[NDArray[np.int64]]:
        """``match(query, r)`` for every reference, in order; backends may share work."""
        ...
