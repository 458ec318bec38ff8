"""An in-memory ``ReferenceStore``: evaluation scripts and engine tests use it without a DB."""

from __future__ import annotations

import numpy as np

from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.references import ReferenceData, ReferenceView
from services.retrieval.index import RetrievalIndex


class MemoryReferenceStore:
    """References kept in a dict, keyed by name (which doubles as the image id)."""

    def __init__(self) -> None:
        self._views: dict[str, ReferenceView] = {}
        self._descriptors: dict[str, np.ndarray] = {}

    def add(self, name: str, camera: Camera, cam_from_world: Rigid3d, data: ReferenceData) -> None:
        self._views[name] = ReferenceView(
            name, name, camera, cam_from_world, data.features, data.depth
        )
        self._descriptors[name] = data.global_descriptor

    def remove(self, name: str) -> None:
        self._views.pop(name, None)
        self._descriptors.pop(name, None)

    def retrieval_index(self) -> RetrievalIndex:
        ids = list(self._views)
        if not ids:
            return RetrievalIndex([], np.zeros((0, 1), np.float32), np.zeros((0, 3)))
        return RetrievalIndex(
            image_ids=ids,
            descriptors=np.stack([self._descriptors[i] for i in ids]).astype(np.float32),
            centers=np.stack([self._views[i].cam_from_world.center for i in ids]),
        )

    def load_references(self, image_ids: list[str]) -> list[ReferenceView]:
        return [self._views[i] for i in image_ids if i in self._views]
