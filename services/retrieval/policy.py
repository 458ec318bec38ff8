"""When a map's VLAD vocabulary is (re)trained: the policy, apart from where it is stored."""

from __future__ import annotations

NUM_CENTERS = 8  # K: 8 × 128-D descriptors = 1024-D VLAD (recall@10 100 % on redkitchen)
MIN_IMAGES = 16  # a map with fewer references keeps thumbnail retrieval
GROWTH = 4  # retrain when the map has this many times the references it was trained on
TRAINING_IMAGES = 200  # references whose descriptors train the vocabulary (random sample)


def training_due(num_references: int, trained_images: int | None) -> bool:
    """Whether a map of ``num_references`` needs a new vocabulary; ``trained_images`` is the
    size the current one was trained at (None: the map has none)."""
    if num_references < MIN_IMAGES:
        return False
    return trained_images is None or num_references >= GROWTH * trained_images
