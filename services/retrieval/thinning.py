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

That spacing is the map's, not the depth of the scene, so by position alone a sparse map
would lose the references next to the first-ranked, which lie nearest the query. A near-copy
also looks the same way: a closer candidate is skipped only where its optical axis lies
within ``NEAR_COPY_TURN_DEG`` of the kept one's. A handheld capture turns as it moves, more
between frames captured further apart (redkitchen: a median 1.1–1.4° between neighbouring map
frames at one frame in 5, 5.2–6.6° at one in 25;
``docs/benchmarks/2026-11-30-map-density.md``).

References on a track they look along (a vehicle's frames: ``TRACK_NEIGHBOURS`` candidates
nearest the first-ranked one in forward motion, ``services.estimators.position_conditioning``)
are no near-copies of each other: each step moves the camera into the scene, and the ones
around the first-ranked share the most of its view. There a candidate is skipped only closer
than ``TRACK_SPACING_FACTOR`` × the spacing, which keeps a track of even spacing whole. At the
handheld factor the track lost every other reference near the query and appearance filled
the slots with frames from elsewhere along the road (kitti05: more than half of the ten
retrieved lay over 15 m from the query; ``docs/benchmarks/2026-11-30-track-retrieval.md``).

A query whose answer stays unsure is matched again against a wider spread
(``WIDER_SPACING_FACTOR``, ``services.localization.widen``): where a map holds several passes
through a place, the closest-spaced references retrieved first can all come from one pass
along one line, and the estimators then disagree on the position along it.
"""

from __future__ import annotations

import numpy as np

from services.estimators.position_conditioning import reference_layout
from services.retrieval.contracts import RetrievalIndex
from services.retrieval.search import PositionPrior, search_index
from services.types import Float32Array, FloatArray, IntArray

# a closer candidate is no near-copy of a kept one where their optical axes differ by more
NEAR_COPY_TURN_DEG = 3.0
# candidates searched per reference asked for
CANDIDATES_PER_REFERENCE = 3
# kept references lie at least this many times the candidates' median spacing apart
SPACING_FACTOR = 1.5
# the spacing of the second retrieval of a query whose first answer is unsure
WIDER_SPACING_FACTOR = 3.0
# on a track looked along: below 1, references of even spacing are all kept
TRACK_SPACING_FACTOR = 0.75
# the candidates nearest the first-ranked (itself included) whose layout tells a track
TRACK_NEIGHBOURS = 5


def thin_references(
    rows: IntArray,
    scores: Float32Array,
    centers: FloatArray,
    k: int,
    spacing_factor: float = SPACING_FACTOR,
    axes: FloatArray | None = None,
) -> tuple[IntArray, Float32Array]:
    """The first ``k`` of ``rows`` (ranked best first, with their ``scores``) that keep
    ``spacing_factor`` × the candidates' spacing from each other; ``centers``: (N, 3) camera
    centres indexed by ``rows``. With ``axes`` ((N, 3) optical axes, the same indexing), a
    candidate closer than that is kept all the same where it looks more than
    ``NEAR_COPY_TURN_DEG`` away from each kept one that close. When fewer than ``k`` are kept,
    the skipped ones fill up the rest in rank order (the result then has min(k, len(rows))).
    """
    if len(rows) <= k:
        return rows[:k], scores[:k]
    points = centers[rows]
    distances = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=2)
    np.fill_diagonal(distances, np.inf)
    spacing = spacing_factor * float(np.median(distances.min(axis=1)))
    close = distances < spacing
    if axes is not None:
        directions = axes[rows]
        close &= directions @ directions.T > np.cos(np.radians(NEAR_COPY_TURN_DEG))
    kept: list[int] = []
    for i in range(len(rows)):
        if not close[i, kept].any():
            kept.append(i)
            if len(kept) == k:
                break
    if len(kept) < k:
        taken = set(kept)
        skipped = [i for i in range(len(rows)) if i not in taken]
        kept = sorted(kept + skipped[: k - len(kept)])
    order = np.asarray(kept, np.int64)
    return rows[order], scores[order]


def on_track(centers: FloatArray, axes: FloatArray) -> bool:
    """Whether the ``TRACK_NEIGHBOURS`` of these (N, 3) centres nearest the first (itself
    included), with their (N, 3) optical axes, lie on a line they look along."""
    nearest = np.argsort(np.linalg.norm(centers - centers[0], axis=1))[:TRACK_NEIGHBOURS]
    layout = reference_layout(centers[nearest], axes[nearest], np.ones(len(nearest)))
    return layout.forward_motion


def search_thinned(
    index: RetrievalIndex,
    query: Float32Array,
    k: int,
    prior: PositionPrior | None = None,
    spacing_factor: float | None = None,
) -> tuple[IntArray, Float32Array]:
    """``search_index`` for ``CANDIDATES_PER_REFERENCE`` × ``k`` candidates, thinned to ``k``
    by ``thin_references`` at ``spacing_factor`` (None: ``SPACING_FACTOR``, or
    ``TRACK_SPACING_FACTOR`` where the candidates around the first-ranked lie ``on_track``; by
    these rules a closer candidate looking elsewhere is kept, see ``thin_references``; a
    factor given spreads by position alone): row indices into ``index`` and their scores, best
    first."""
    rows, scores = search_index(index, query, CANDIDATES_PER_REFERENCE * k, prior)
    axes = None
    if spacing_factor is None:
        axes = index.axes
        track = axes is not None and len(rows) > 1 and on_track(index.centers[rows], axes[rows])
        spacing_factor = TRACK_SPACING_FACTOR if track else SPACING_FACTOR
    return thin_references(rows, scores, index.centers, k, spacing_factor, axes)
