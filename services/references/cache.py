"""Reference features kept decoded in memory between requests: a thread-safe LRU cache
bounded in bytes.

A reference's stored features never change after it is added (a new image gets a new id), so
an entry stays right until the reference is deleted. Deletes drop entries, and the store
checks every id against the database before it serves an entry, so a deleted reference is
never served even when another process deleted it.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

from services.features.base import LocalFeatures
from services.types import Float32Array


@dataclass(frozen=True)
class CachedFeatures:
    """A reference's decoded features and depth ((H, W) float32 metres, or None); arrays are
    read-only, shared by every request that reads them."""

    features: LocalFeatures
    depth: Float32Array | None

    @property
    def nbytes(self) -> int:
        f = self.features
        arrays = (f.keypoints, f.descriptors, f.scores, self.depth)
        return sum(a.nbytes for a in arrays if a is not None)


@dataclass(frozen=True)
class CacheStats:
    entries: int
    bytes: int
    max_bytes: int
    hits: int
    misses: int


class ReferenceFeatureCache:
    """Decoded features by (map id, image id); the least recently used go once the arrays
    held exceed ``max_bytes`` (0 disables the cache)."""

    def __init__(self, max_bytes: int) -> None:
        if max_bytes < 0:
            raise ValueError(f"max_bytes must be >= 0, got {max_bytes}")
        self.max_bytes = max_bytes
        self._entries: OrderedDict[tuple[str, str], CachedFeatures] = OrderedDict()
        self._bytes = 0
        self._hits = 0
        self._misses = 0
        self._generation = 0  # changes with every discard
        self._lock = threading.Lock()

    def generation(self) -> int:
        """A token to take before reading the store and give back to ``put``: an entry read
        before a discard that raced with it is not kept."""
        with self._lock:
            return self._generation

    def get(self, map_id: str, image_id: str) -> CachedFeatures | None:
        with self._lock:
            entry = self._entries.get((map_id, image_id))
            if entry is None:
                self._misses += 1
                return None
            self._entries.move_to_end((map_id, image_id))
            self._hits += 1
            return entry

    def put(self, map_id: str, image_id: str, entry: CachedFeatures, generation: int) -> None:
        """Keeps ``entry`` (made read-only) unless a discard ran since ``generation`` was
        taken or it alone exceeds the bound; evicts the least recently used past the bound."""
        size = entry.nbytes
        if size > self.max_bytes:
            return
        f = entry.features
        for array in (f.keypoints, f.descriptors, f.scores, entry.depth):
            if array is not None:
                array.setflags(write=False)
        with self._lock:
            if generation != self._generation:
                return
            key = (map_id, image_id)
            old = self._entries.pop(key, None)
            if old is not None:
                self._bytes -= old.nbytes
            self._entries[key] = entry
            self._bytes += size
            while self._bytes > self.max_bytes:
                _, evicted = self._entries.popitem(last=False)
                self._bytes -= evicted.nbytes

    def discard(self, map_id: str, image_ids: list[str] | None = None) -> None:
        """Drops the map's entries for ``image_ids`` (None: all of the map's)."""
        with self._lock:
            self._generation += 1
            if image_ids is None:
                keys = [k for k in self._entries if k[0] == map_id]
            else:
                keys = [(map_id, i) for i in image_ids if (map_id, i) in self._entries]
            for key in keys:
                self._bytes -= self._entries.pop(key).nbytes

    def stats(self) -> CacheStats:
        with self._lock:
            return CacheStats(
                len(self._entries), self._bytes, self.max_bytes, self._hits, self._misses
            )
