"""Reference images for the match refinement (``services.matching.refinement``): decoded from
the originals a store keeps, at the refinement's resolution, and the most recently used kept in
memory (a thread-safe LRU cache bounded in bytes).

An original never changes under its key (a new image gets a new id), so an entry stays right
for as long as it is kept; a deleted reference's entry is never asked for again and ages out.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from collections.abc import Callable

from services.errors import InvalidInputError
from services.imaging.decode import decode_image_reduced
from services.matching.refinement import RefinementImage, refinement_image
from services.references.store import ReferenceStore, ReferenceView

logger = logging.getLogger(__name__)


class ReferenceImageCache:
    """Refinement images by (original key, longer side); the least recently used go once the
    pixels held exceed ``max_bytes`` (0 keeps none)."""

    def __init__(self, max_bytes: int) -> None:
        if max_bytes < 0:
            raise ValueError(f"max_bytes must be >= 0, got {max_bytes}")
        self.max_bytes = max_bytes
        self._entries: OrderedDict[tuple[str, int], RefinementImage] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key: str, side: int) -> RefinementImage | None:
        with self._lock:
            entry = self._entries.get((key, side))
            if entry is not None:
                self._entries.move_to_end((key, side))
            return entry

    def put(self, key: str, side: int, image: RefinementImage) -> None:
        """Keeps ``image`` (made read-only) unless it alone exceeds the bound; evicts the
        least recently used past the bound."""
        if image.nbytes > self.max_bytes:
            return
        image.gray.setflags(write=False)
        with self._lock:
            old = self._entries.pop((key, side), None)
            if old is not None:
                self._bytes -= old.nbytes
            self._entries[(key, side)] = image
            self._bytes += image.nbytes
            while self._bytes > self.max_bytes:
                _, evicted = self._entries.popitem(last=False)
                self._bytes -= evicted.nbytes

    @property
    def bytes(self) -> int:
        with self._lock:
            return self._bytes


def reference_images(
    store: ReferenceStore,
    references: list[ReferenceView],
    side: int,
    max_pixels: int,
    cache: ReferenceImageCache,
) -> Callable[[str], RefinementImage | None]:
    """A reference's image by id, among ``references``, at longer side ``side`` at most: from
    ``cache``, else decoded from the original ``store`` keeps (and kept). None for a reference
    without an original, or whose original cannot be read or decoded (logged)."""
    views = {reference.image_id: reference for reference in references}

    def image(image_id: str) -> RefinementImage | None:
        view = views.get(image_id)
        if view is None or view.original_key is None:
            return None
        cached = cache.get(view.original_key, side)
        if cached is not None:
            return cached
        data = store.read_original(view.original_key)
        if data is None:
            return None
        try:
            decoded = decode_image_reduced(data, max_pixels, side)
        except InvalidInputError as exc:
            logger.warning("reference %s: original not refined against: %s", view.name, exc)
            return None
        loaded = refinement_image(decoded.rgb, decoded.width, decoded.height, side)
        cache.put(view.original_key, side, loaded)
        return loaded

    return image
