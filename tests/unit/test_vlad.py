"""VLAD global descriptor and vocabulary training."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from services.retrieval.policy import num_centers
from services.retrieval.vlad import encode, kmeans, raw_vlad, train_vocabulary


def _images(rng: np.random.Generator, count: int, n: int = 200) -> list[NDArray[np.float32]]:
    out = []
    for _ in range(count):
        d = rng.standard_normal((n, 32)).astype(np.float32)
        out.append(d / np.linalg.norm(d, axis=1, keepdims=True))
    return out


class TestKmeans:
    def test_recovers_separated_clusters(self) -> None:
        rng = np.random.default_rng(1)
        truth = np.array([[0, 0], [10, 0], [0, 10]], np.float32)
        points = (truth[rng.integers(3, size=600)] + 0.1 * rng.standard_normal((600, 2))).astype(
            np.float32
        )
        centers = kmeans(points, 3, np.random.default_rng(0))
        order = np.lexsort((centers[:, 1], centers[:, 0]))
        expected = truth[np.lexsort((truth[:, 1], truth[:, 0]))]
        np.testing.assert_allclose(centers[order], expected, atol=0.05)

    def test_as_many_points_as_centres_gives_the_points(self) -> None:
        points = np.random.default_rng(2).standard_normal((5, 4)).astype(np.float32)
        centers = kmeans(points, 5, np.random.default_rng(0))
        np.testing.assert_array_equal(centers[np.lexsort(centers.T)], points[np.lexsort(points.T)])

    def test_same_generator_state_same_centres(self) -> None:
        points = np.random.default_rng(3).standard_normal((500, 8)).astype(np.float32)
        a = kmeans(points, 6, np.random.default_rng(5))
        np.testing.assert_array_equal(a, kmeans(points, 6, np.random.default_rng(5)))
        assert not np.array_equal(a, kmeans(points, 6, np.random.default_rng(6)))

    def test_too_few_points(self) -> None:
        with pytest.raises(ValueError, match="at least k=4"):
            kmeans(np.zeros((3, 2), np.float32), 4, np.random.default_rng(0))


class TestVlad:
    def test_shape_and_unit_norm(self) -> None:
        images = _images(np.random.default_rng(0), 5)
        vocab = train_vocabulary(images, num_centers=8, dimension=None)
        vector = encode(images[0], vocab)
        assert vector.shape == (8 * 32,) and vector.dtype == np.float32
        assert vocab.dimension == 8 * 32
        assert abs(float(np.linalg.norm(vector)) - 1.0) < 1e-5

    def test_identical_images_score_one_and_different_less(self) -> None:
        images = _images(np.random.default_rng(0), 5)
        vocab = train_vocabulary(images, num_centers=8, dimension=None)
        a, b = encode(images[0], vocab), encode(images[0].copy(), vocab)
        assert float(a @ b) == pytest.approx(1.0, abs=1e-5)
        assert float(a @ encode(images[1], vocab)) < 0.9

    def test_hand_computed(self) -> None:
        centers = np.array([[1, 0], [0, 1]], np.float32)
        descriptors = np.array([[0.8, 0.6], [0.6, 0.8]], np.float32)
        # residuals (-0.2, 0.6) to centre 0 and (0.6, -0.2) to centre 1, intra-normalised,
        # signed square root, then L2-normalised
        block = np.array([-0.2, 0.6]) / np.hypot(0.2, 0.6)
        block = np.sign(block) * np.sqrt(np.abs(block))
        expected = np.concatenate([block, block[::-1]])
        expected /= np.linalg.norm(expected)
        np.testing.assert_allclose(raw_vlad(descriptors, centers), expected, atol=1e-6)

    def test_empty_image_is_zero(self) -> None:
        vocab = train_vocabulary(
            _images(np.random.default_rng(0), 3), num_centers=4, dimension=None
        )
        assert not encode(np.zeros((0, 32), np.float32), vocab).any()

    def test_batch_equals_loop(self) -> None:
        images = _images(np.random.default_rng(2), 6)
        vocab = train_vocabulary(images, num_centers=8, dimension=4)
        stacked = np.stack([encode(d, vocab) for d in images])
        assert stacked.shape == (6, 4)
        for i, d in enumerate(images):
            np.testing.assert_array_equal(stacked[i], encode(d, vocab))

    def test_whitened_dimension_capped_by_images(self) -> None:
        images = _images(np.random.default_rng(3), 6)
        vocab = train_vocabulary(images, num_centers=8, dimension=512)
        assert vocab.dimension <= 5
        assert abs(float(np.linalg.norm(encode(images[0], vocab))) - 1.0) < 1e-5


class TestTrainingDeterminism:
    def test_same_seed_same_vocabulary(self) -> None:
        images = _images(np.random.default_rng(4), 4)
        a = train_vocabulary(images, num_centers=8, dimension=3, seed=7)
        b = train_vocabulary(images, num_centers=8, dimension=3, seed=7)
        np.testing.assert_array_equal(a.centers, b.centers)
        np.testing.assert_array_equal(a.projection, b.projection)

    def test_other_seed_other_vocabulary(self) -> None:
        images = _images(np.random.default_rng(4), 4)
        a = train_vocabulary(images, num_centers=8, dimension=None, seed=7)
        b = train_vocabulary(images, num_centers=8, dimension=None, seed=8)
        assert not np.array_equal(a.centers, b.centers)


def test_vocabulary_size_follows_the_descriptor_length() -> None:
    # 128-D descriptors (SIFT, ALIKED, DISK) keep 1024-D VLAD; XFeat's 64-D ones get 64 centres
    assert num_centers(128) * 128 == 1024
    assert num_centers(64) * 64 == 4096
