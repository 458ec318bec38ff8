"""Approximate top-k search for large maps: a faiss inverted-file index with 8-bit scalar
quantized vectors (IVF-SQ8, inner product on unit vectors = cosine) finds ``rerank × k``
candidates, which are rescored exactly against the snapshot's float32 rows (the 8-bit codes
alone swap near-ties: among views of one place the 10th and 11th best differ by ~1e-3).

The faiss index is trained once per (map, model, vocabulary version) and then kept current by
``remove_ids`` / ``add_with_ids`` as references come and go. Each vector lives in a *slot*
(its faiss id), which never moves; a ``RetrievalIndex`` snapshot carries its own slot → row
table, so a search running on an older snapshot while the faiss index is updated can only
return rows of that snapshot (slots added since map to -1 and are skipped, slots removed are
not returned). A position prior is applied inside faiss as an ``IDSelectorBitmap`` over slots.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import faiss
import numpy as np

from services.types import BoolArray, Float32Array, IntArray

TRAINING_POINTS_PER_LIST = 256  # k-means sample per inverted list (faiss samples 256 at most)
REBUILD_GROWTH = 4  # retrain the coarse quantizer when the index grew this many times


@dataclass(frozen=True)
class AnnOptions:
    """``min_references``: maps with fewer references are searched exactly. ``nprobe``:
    inverted lists visited per query (more: higher recall, slower). ``rerank``: candidates per
    wanted result that are rescored exactly."""

    min_references: int = 50_000
    nprobe: int = 128
    rerank: int = 4


class AnnIndex:
    """A faiss IVF-SQ8 index over unit vectors, addressed by slot ids; thread-safe."""

    def __init__(
        self, vectors: Float32Array, options: AnnOptions, seed: int = 0, nlist: int | None = None
    ) -> None:
        """Train on (a sample of) ``vectors`` (N, D) float32 unit rows and add them all as
        slots 0..N-1. ``nlist``: inverted lists (default √N)."""
        n, dim = vectors.shape
        nlist = nlist or max(1, int(np.sqrt(n)))
        quantizer = faiss.IndexFlatIP(dim)
        index = faiss.IndexIVFScalarQuantizer(
            quantizer, dim, nlist, faiss.ScalarQuantizer.QT_8bit, faiss.METRIC_INNER_PRODUCT
        )
        index.cp.seed = seed
        sample = min(n, nlist * TRAINING_POINTS_PER_LIST)
        picked = np.random.default_rng(seed).choice(n, sample, replace=False)
        index.train(np.ascontiguousarray(vectors[np.sort(picked)]))
        index.nprobe = options.nprobe
        index.add_with_ids(np.ascontiguousarray(vectors), np.arange(n, dtype=np.int64))
        self._index = index
        self._lock = threading.Lock()
        self.trained_size = n
        self.next_slot = n
        self.options = options

    @property
    def ntotal(self) -> int:
        return int(self._index.ntotal)

    def nbytes(self) -> int:
        """Bytes of the codes and ids held (the coarse centroids aside)."""
        return self.ntotal * (int(self._index.code_size) + 8)

    def add(self, vectors: Float32Array) -> IntArray:
        """Add (M, D) unit rows; returns their (M,) new slots."""
        with self._lock:
            slots = np.arange(self.next_slot, self.next_slot + vectors.shape[0], dtype=np.int64)
            self._index.add_with_ids(np.ascontiguousarray(vectors, np.float32), slots)
            self.next_slot += vectors.shape[0]
        return slots

    def remove(self, slots: IntArray) -> None:
        if slots.size:
            with self._lock:
                ids = np.ascontiguousarray(slots, np.int64)
                self._index.remove_ids(faiss.IDSelectorBatch(ids.size, faiss.swig_ptr(ids)))

    def search(
        self, query: Float32Array, k: int, allowed_slots: BoolArray | None = None
    ) -> tuple[IntArray, Float32Array]:
        """Up to ``k`` (slots, scores) best first; ``allowed_slots`` ((next_slot,) bool or
        shorter): only those slots qualify."""
        params = faiss.SearchParametersIVF()
        params.nprobe = self.options.nprobe
        bitmap = None
        if allowed_slots is not None:
            bitmap = np.packbits(allowed_slots, bitorder="little")
            params.sel = faiss.IDSelectorBitmap(allowed_slots.size, faiss.swig_ptr(bitmap))
        with self._lock:
            scores, slots = self._index.search(
                np.ascontiguousarray(query[None, :], np.float32), k, params=params
            )
        keep = slots[0] >= 0
        return slots[0][keep].astype(np.int64), scores[0][keep].astype(np.float32)


@dataclass(frozen=True)
class AnnView:
    """An ``AnnIndex`` as one ``RetrievalIndex`` snapshot sees it.

    Attributes:
        index: the shared faiss index.
        row_of_slot: (S,) int64 row of each slot in the snapshot, -1 when not in it.
        slot_of_row: (N,) int64 slot of each row.
    """

    index: AnnIndex
    row_of_slot: IntArray
    slot_of_row: IntArray

    @classmethod
    def build(cls, vectors: Float32Array, options: AnnOptions) -> AnnView:
        n = vectors.shape[0]
        rows = np.arange(n, dtype=np.int64)
        return cls(AnnIndex(vectors, options), rows, rows.copy())

    def updated(self, previous_rows: IntArray, descriptors: Float32Array) -> AnnView:
        """The view of a newer snapshot whose row ``i`` was row ``previous_rows[i]`` of this
        one, or is new (-1); ``descriptors``: (N, D) rows of the newer snapshot (only the new
        ones are read). The faiss index drops the rows the newer snapshot lacks and gains the
        new ones."""
        known = previous_rows >= 0
        dropped = np.ones(self.slot_of_row.size, bool)
        dropped[previous_rows[known]] = False
        self.index.remove(self.slot_of_row[dropped])
        slot_of_row = np.empty(previous_rows.size, np.int64)
        slot_of_row[known] = self.slot_of_row[previous_rows[known]]
        new_rows = np.flatnonzero(~known)
        if new_rows.size:
            slot_of_row[new_rows] = self.index.add(descriptors[new_rows])
        row_of_slot = np.full(self.index.next_slot, -1, np.int64)
        row_of_slot[slot_of_row] = np.arange(slot_of_row.size)
        return AnnView(self.index, row_of_slot, slot_of_row)

    def stale(self) -> bool:
        """Whether the map outgrew the sample the coarse quantizer was trained on."""
        return bool(self.slot_of_row.size >= REBUILD_GROWTH * self.index.trained_size)

    def search(
        self,
        query: Float32Array,
        k: int,
        descriptors: Float32Array,
        allowed_rows: BoolArray | None = None,
    ) -> tuple[IntArray, Float32Array]:
        """Up to ``k`` (rows, exact scores) of this snapshot, best first; ``descriptors``: its
        (N, D) float32 rows, which rescore the candidates."""
        allowed = None
        if allowed_rows is not None:
            allowed = np.zeros(self.row_of_slot.size, bool)
            allowed[self.slot_of_row[allowed_rows]] = True
        slots, _ = self.index.search(query, k * self.index.options.rerank, allowed)
        slots_known = slots < self.row_of_slot.size
        rows = np.full(slots.size, -1, np.int64)
        rows[slots_known] = self.row_of_slot[slots[slots_known]]
        rows = rows[rows >= 0]
        scores = (descriptors[rows] @ query).astype(np.float32)
        best = np.argsort(-scores, kind="stable")[:k]
        return rows[best], scores[best]
