"""Near-duplicate references thinned out of the retrieved set.

Consecutive frames of a capture look alike, so a retrieval ranked by appearance alone fills
its top-k with one cluster of references a few centimetres apart. The structureless
estimators take the query's scale and position from the baseline between references: ten
near-copies of one view give them little of it (E5+1 then answers ``degenerate_geometry`` or
a pose off along the cluster's line of sight) and spend the matching on redundant pairs.

``thin_references`` walks more candidates than are asked for, best first, and skips one whose
camera centre lies closer to an already kept reference than ``SPACING_FACTOR`` × the
candidates' own spacing (the median distance from each candidate to its nearest other
candidate), so the rule needs no unit: it scales with how densely the map was captured where
the query looks.

A query whose answer stays unsure is matched again against a wider spread
(``WIDER_SPACING_FACTOR``, ``services.localization.widen``): where a map holds several passes
through a place, the closest-spaced references retrieved first can all come from one pass
along one line, and the estimators then disagree on the position along it.
"""

from __future__ import annotations

import numpy as np

from services.retrieval.contracts import RetrievalIndex
from services.retrieval.search import PositionPrior, search_index
from services.types import Float32Array, FloatArray, IntArray

# candidates searched per reference asked for
CANDIDATES_PER_REFERENCE = 3
# kept references lie at least this many times the candidates' median spacing apart
SPACING_FACTOR = 1.5
# the spacing of the second retrieval of a query whose first answer is unsure
WIDER_SPACING_FACTOR = 3.0


def thin_references(
    rows: IntArray,
    scores: Float32Array,
    centers: FloatArray,
    k: int,
    spacing_factor: float = SPACING_FACTOR,
) -> tuple[IntArray, Float32Array]:
    """The first ``k`` of ``rows`` (ranked best first, with their ``scores``) that keep
    ``spacing_factor`` × the candidates' spacing; ``centers``: (N, 3) camera centres indexed
    by ``rows``. When fewer keep it, the skipped ones fill up the rest in rank order (the
    result then has min(k, len(rows))).
    """
    if len(rows) <= k:
        return rows[:k], scores[:k]
    points = centers[rows]
    distances = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=2)
    np.fill_diagonal(distances, np.inf)
    spacing = spacing_factor * float(np.median(distances.min(axis=1)))
    kept: list[int] = []
    for i in range(len(rows)):
        if not kept or distances[i, kept].min() >= spacing:
            kept.append(i)
            if len(kept) == k:
                break
    if len(kept) < k:
        taken = set(kept)
        skipped = [i for i in range(len(rows)) if i not in taken]
        kept = sorted(kept + skipped[: k - len(kept)])
    order = np.asarray(kept, np.int64)
    return rows[order], scores[order]


def search_thinned(
    index: RetrievalIndex,
    query: Float32Array,
    k: int,
    prior: PositionPrior | None = None,
    spacing_factor: float = SPACING_FACTOR,
) -> tuple[IntArray, Float32Array]:
    """``search_index`` for ``CANDIDATES_PER_REFERENCE`` × ``k`` candidates, thinned to ``k``
    by ``thin_references`` at ``spacing_factor``: row indices into ``index`` and their
    scores, best first."""
    rows, scores = search_index(index, query, CANDIDATES_PER_REFERENCE * k, prior)
    return thin_references(rows, scores, index.centers, k, spacing_factor)
