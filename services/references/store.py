"""The contract between the engine and whatever stores a map's reference images (the database
in the service, memory in tests): what is stored per reference and how the pipeline reads it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from services.features.base import LocalFeatures
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.retrieval.contracts import RetrievalIndex
from services.types import Float32Array


@dataclass(frozen=True)
class ReferenceData:
    """Everything stored for a reference image besides its name, camera and pose.

    Attributes:
        features: its local features.
        global_descriptor: (D,) float32 unit vector.
        depth: (H, W) float32 metres (0 = unknown), or None.
        feature_model: name of the extractor that made ``features``.
        descriptor_model: name of the global-descriptor backend.
    """

    features: LocalFeatures
    global_descriptor: Float32Array
    depth: Float32Array | None
    feature_model: str
    descriptor_model: str


@dataclass(frozen=True)
class ReferenceView:
    """A stored reference image as the pipeline needs it. ``original_key``: where the store
    keeps the image as uploaded (``ReferenceStore.read_original``), None when it keeps none;
    the image under a key never changes."""

    image_id: str
    name: str
    camera: Camera
    cam_from_world: Rigid3d
    features: LocalFeatures
    depth: Float32Array | None
    original_key: str | None = None


class ReferenceStore(Protocol):
    """Read access to one map's references, restricted to the localizer's feature models."""

    def retrieval_index(self) -> RetrievalIndex: ...

    def load_references(self, image_ids: list[str]) -> list[ReferenceView]:
        """The references with these ids, in that order; ids deleted meanwhile are skipped."""
        ...

    def read_original(self, key: str) -> bytes | None:
        """The image uploaded under ``key`` (a view's ``original_key``), as sent, or None
        when it cannot be read."""
        ...
