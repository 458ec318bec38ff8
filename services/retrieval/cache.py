"""Retrieval indexes kept in memory between requests and caught up incrementally from the
store they come from."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np

from services.retrieval.ann import AnnOptions, AnnView
from services.retrieval.contracts import EMPTY_INDEX, RetrievalIndex, VocabularyState, empty_index
from services.retrieval.training import BackgroundTrainer


class IndexSource(Protocol):
    """Where one map's index comes from (the database in the service)."""

    map_id: str
    feature_model: str
    descriptor_model: str

    def revision(self) -> int | None:
        """A number every add and delete changes (any process); None: the map is gone."""
        ...

    def reference_ids(self) -> list[str]: ...

    def vocabulary(self) -> VocabularyState | None:
        """The published vocabulary the index uses (None: global descriptors)."""
        ...

    def load_index(
        self, vocabulary: VocabularyState | None, only_ids: list[str] | None = None
    ) -> RetrievalIndex: ...


@dataclass(frozen=True)
class CacheSize:
    """What a ``RetrievalIndexCache`` holds: indexes (one per map and model pair), their
    references, and the bytes of their descriptor and centre arrays."""

    indexes: int
    references: int
    nbytes: int


@dataclass
class _CachedIndex:
    revision: int
    index: RetrievalIndex
    lock: threading.Lock = field(default_factory=threading.Lock)


class RetrievalIndexCache:
    """Retrieval indexes of every map this process localizes against, kept in memory.

    Each request reads the map's revision (one indexed row; every add and delete bumps it, in
    any process). While it is unchanged the cached index is served as is; otherwise the index
    catches up: the ids of the map's references are listed, descriptors are read only for the
    new ones, and deleted ones are dropped. The revision is read before the ids, so a write
    racing with the catch-up leaves the cache at most one request behind, never wrong for good.

    With ``ann`` options, an index of at least ``ann.min_references`` references also keeps an
    approximate faiss index (``RetrievalIndex.ann``), updated by the same catch-up. With a
    ``builder``, that index is trained in the background (50 s at a million references here)
    while requests go on with exact search, or with the index the map outgrew; without one, in
    the request that needs it.
    """

    def __init__(
        self, ann: AnnOptions | None = None, builder: BackgroundTrainer | None = None
    ) -> None:
        self.ann = ann
        self.builder = builder
        self._entries: dict[tuple[str, str, str], _CachedIndex] = {}
        self._lock = threading.Lock()

    def index(self, store: IndexSource) -> RetrievalIndex:
        key = (store.map_id, store.feature_model, store.descriptor_model)
        revision = store.revision()
        if revision is None:  # the map is gone
            with self._lock:
                self._entries.pop(key, None)
            return EMPTY_INDEX
        with self._lock:
            entry = self._entries.setdefault(key, _CachedIndex(-1, EMPTY_INDEX))
        with entry.lock:
            if entry.revision != revision:
                vocabulary = store.vocabulary()
                version = 0 if vocabulary is None else vocabulary.version
                if version != entry.index.vocabulary_version:  # other descriptors: reload
                    index = store.load_index(vocabulary)
                else:
                    index = _catch_up(entry.index, store, vocabulary)
                entry.index = self._with_ann(key, entry, index)
                entry.revision = revision
            return entry.index

    def _with_ann(
        self, key: tuple[str, str, str], entry: _CachedIndex, index: RetrievalIndex
    ) -> RetrievalIndex:
        """``index`` with an approximate index when it is large enough: the one it has, unless
        it has none yet or outgrew it; then a new one is built (in the background with a
        builder). A small index searches exactly."""
        options = self.ann
        if options is None or len(index.image_ids) < options.min_references:
            return index if index.ann is None else replace(index, ann=None)
        if index.ann is not None and not index.ann.stale():
            return index
        if self.builder is None:
            return replace(index, ann=AnnView.build(index.descriptors, options))
        self.builder.schedule(key, lambda: self._build_ann(entry, index, options))
        return index

    @staticmethod
    def _build_ann(entry: _CachedIndex, snapshot: RetrievalIndex, options: AnnOptions) -> None:
        """Train an approximate index on ``snapshot`` and hand it to the entry's current index,
        caught up with the adds and deletes made meanwhile (dropped when the descriptors were
        replaced or the map shrank below the threshold)."""
        view = AnnView.build(snapshot.descriptors, options)
        row_before = {image_id: row for row, image_id in enumerate(snapshot.image_ids)}
        with entry.lock:
            current = entry.index
            if (
                current.vocabulary_version != snapshot.vocabulary_version
                or len(current.image_ids) < options.min_references
            ):
                return
            previous_rows = np.array([row_before.get(i, -1) for i in current.image_ids], np.int64)
            entry.index = replace(current, ann=view.updated(previous_rows, current.descriptors))

    def size(self) -> CacheSize:
        with self._lock:
            indexes = [entry.index for entry in self._entries.values()]
        return CacheSize(
            indexes=len(indexes),
            references=sum(len(index.image_ids) for index in indexes),
            nbytes=sum(
                index.descriptors.nbytes
                + index.centers.nbytes
                + (0 if index.axes is None else index.axes.nbytes)
                + (0 if index.ann is None else index.ann.index.nbytes())
                for index in indexes
            ),
        )


def _catch_up(
    index: RetrievalIndex, store: IndexSource, vocabulary: VocabularyState | None
) -> RetrievalIndex:
    current = set(store.reference_ids())
    keep = [i for i, image_id in enumerate(index.image_ids) if image_id in current]
    new_ids = sorted(current - set(index.image_ids))
    added = store.load_index(vocabulary, new_ids) if new_ids else EMPTY_INDEX
    if not added.image_ids:
        if len(keep) == len(index.image_ids):
            return index
        if not keep:
            return empty_index(vocabulary)
    parts = [(index.descriptors[keep], index.centers[keep])] if keep else []
    if added.image_ids:
        parts.append((added.descriptors, added.centers))
    descriptors = np.concatenate([d for d, _ in parts])
    ann = index.ann
    if ann is not None:
        previous_rows = np.concatenate(
            [np.asarray(keep, np.int64), np.full(len(added.image_ids), -1, np.int64)]
        )
        ann = ann.updated(previous_rows, descriptors)
    axes = None
    if index.axes is not None and added.axes is not None:
        axes = np.concatenate([index.axes[keep], added.axes])
    return replace(
        index,
        image_ids=[index.image_ids[i] for i in keep] + added.image_ids,
        descriptors=descriptors,
        centers=np.concatenate([c for _, c in parts]),
        ann=ann,
        axes=axes,
    )
