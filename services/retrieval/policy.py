"""When a map's VLAD vocabulary is (re)trained: the policy, apart from where it is stored."""

from __future__ import annotations

NUM_CENTERS = 8  # K for 128-D descriptors (SIFT, ALIKED, DISK): 1024-D VLAD
SHORT_DESCRIPTOR_CENTERS = 64  # K for shorter ones (XFeat's 64-D): 4096-D VLAD
MIN_IMAGES = 16  # a map with fewer references keeps thumbnail retrieval
GROWTH = 4  # retrain when the map has this many times the references it was trained on
TRAINING_IMAGES = 200  # references whose descriptors train the vocabulary (random sample)


def num_centers(descriptor_size: int) -> int:
    """The vocabulary's k-means centres K for descriptors of ``descriptor_size``.

    Measured on redkitchen's suggested split (``python -m tools.benchmarks.retrieval``,
    recall@10 over the 32 queries with a reference within 0.5 m and 30°): SIFT's 128-D
    descriptors reach 100 % at K = 8; XFeat's 2048 64-D ones 87.5 % at K = 8, 84.4 % at 16,
    90.6 % at 32 and 100 % at 64 (recall@1 90.6 %).
    """
    return NUM_CENTERS if descriptor_size >= 128 else SHORT_DESCRIPTOR_CENTERS


def training_due(num_references: int, trained_images: int | None) -> bool:
    """Whether a map of ``num_references`` needs a new vocabulary; ``trained_images`` is the
    size the current one was trained at (None: the map has none)."""
    if num_references < MIN_IMAGES:
        return False
    return trained_images is None or num_references >= GROWTH * trained_images
