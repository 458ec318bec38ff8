"""The in-memory cache of decoded reference features: LRU within its byte bound, discards,
races with discards, threads (issue #13)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from services.features.base import LocalFeatures
from services.references.cache import CachedFeatures, ReferenceFeatureCache


def entry(keypoints: int, depth: bool = False) -> CachedFeatures:
    """keypoints × (8 + 512 + 4) bytes of features, plus a 4 × 4 float32 depth map."""
    features = LocalFeatures(
        np.zeros((keypoints, 2), np.float32),
        np.zeros((keypoints, 128), np.float32),
        np.zeros(keypoints, np.float32),
        (64, 48),
    )
    return CachedFeatures(features, np.zeros((4, 4), np.float32) if depth else None)


def test_nbytes_counts_every_array() -> None:
    assert entry(10).nbytes == 10 * (8 + 512 + 4)
    assert entry(10, depth=True).nbytes == 10 * (8 + 512 + 4) + 64


def test_hit_miss_and_read_only() -> None:
    cache = ReferenceFeatureCache(1 << 20)
    assert cache.get("m", "a") is None
    cache.put("m", "a", entry(10), cache.generation())
    got = cache.get("m", "a")
    assert got is not None and len(got.features) == 10
    assert not got.features.descriptors.flags.writeable
    stats = cache.stats()
    assert (stats.hits, stats.misses, stats.entries) == (1, 1, 1)


def test_least_recently_used_go_first_and_the_bound_holds() -> None:
    size = entry(100).nbytes
    cache = ReferenceFeatureCache(3 * size)
    for name in "abc":
        cache.put("m", name, entry(100), cache.generation())
    cache.get("m", "a")  # b is now the least recently used
    cache.put("m", "d", entry(100), cache.generation())
    assert cache.get("m", "b") is None
    assert all(cache.get("m", n) is not None for n in "acd")
    assert cache.stats().bytes == 3 * size


def test_an_entry_larger_than_the_bound_is_not_kept() -> None:
    cache = ReferenceFeatureCache(entry(10).nbytes)
    cache.put("m", "big", entry(11), cache.generation())
    assert cache.get("m", "big") is None and cache.stats().bytes == 0
    off = ReferenceFeatureCache(0)
    off.put("m", "a", entry(1), off.generation())
    assert off.get("m", "a") is None


def test_discard_images_and_maps() -> None:
    cache = ReferenceFeatureCache(1 << 20)
    for map_id, name in [("m", "a"), ("m", "b"), ("n", "a")]:
        cache.put(map_id, name, entry(5), cache.generation())
    cache.discard("m", ["a", "unknown"])
    assert cache.get("m", "a") is None and cache.get("m", "b") is not None
    cache.discard("m")
    assert cache.get("m", "b") is None and cache.get("n", "a") is not None
    assert cache.stats().bytes == entry(5).nbytes


def test_an_entry_read_before_a_discard_is_not_kept() -> None:
    cache = ReferenceFeatureCache(1 << 20)
    generation = cache.generation()  # a request starts reading "a" from the store …
    cache.discard("m", ["a"])  # … while "a" is deleted
    cache.put("m", "a", entry(5), generation)
    assert cache.get("m", "a") is None


def test_threads_keep_the_bound_and_the_byte_count() -> None:
    size = entry(50).nbytes
    cache = ReferenceFeatureCache(10 * size)
    errors: list[BaseException] = []

    def work(seed: int) -> None:
        rng = np.random.default_rng(seed)
        try:
            for _ in range(2000):
                name = str(rng.integers(40))
                op = rng.integers(3)
                if op == 0:
                    cache.put("m", name, entry(50), cache.generation())
                elif op == 1:
                    cache.get("m", name)
                else:
                    cache.discard("m", [name])
                assert cache.stats().bytes <= 10 * size
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(seed,)) for seed in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors
    stats = cache.stats()
    assert stats.bytes == stats.entries * size <= 10 * size


def test_negative_bound_is_refused() -> None:
    with pytest.raises(ValueError, match="max_bytes"):
        ReferenceFeatureCache(-1)
