import cv2
import numpy as np
import pytest

from services.features.base import LocalFeatures
from services.matching.nearest_neighbor import NearestNeighborMatcher
from services.retrieval.search import PositionPrior, top_k
from services.retrieval.thumbnail import ThumbnailDescriptor


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


class TestTopK:
    def test_order_and_scores(self) -> None:
        rng = np.random.default_rng(0)
        db = _unit(rng.normal(size=(200, 16)))
        query = db[17]
        rows, scores = top_k(query, db, 5)
        assert rows[0] == 17 and np.isclose(scores[0], 1.0)
        assert np.all(np.diff(scores) <= 0)
        assert np.allclose(scores, db[rows] @ query)
        brute = np.argsort(-(db @ query))[:5]
        assert set(rows) == set(brute)

    def test_prior_filters_by_centre(self) -> None:
        db = _unit(np.random.default_rng(1).normal(size=(10, 8)))
        centers = np.zeros((10, 3))
        centers[:, 0] = np.arange(10)
        prior = PositionPrior(np.array([0.0, 0, 0]), radius=2.5)
        rows, _ = top_k(db[9], db, 10, centers, prior)
        assert set(rows) == {0, 1, 2}
        far = PositionPrior(np.array([100.0, 0, 0]), radius=1.0)
        assert top_k(db[0], db, 3, centers, far)[0].size == 0

    def test_empty(self) -> None:
        rows, scores = top_k(np.ones(4, np.float32), np.zeros((0, 4), np.float32), 3)
        assert rows.size == 0 and scores.size == 0


class TestNearestNeighborMatcher:
    def _features(self, desc: np.ndarray) -> LocalFeatures:
        n = desc.shape[0]
        return LocalFeatures(
            np.zeros((n, 2), np.float32), _unit(desc), np.ones(n, np.float32), (640, 480)
        )

    def test_recovers_permutation_and_rejects_ambiguous(self) -> None:
        rng = np.random.default_rng(0)
        ref = rng.normal(size=(50, 32))
        perm = rng.permutation(50)
        query = ref[perm] + 0.01 * rng.normal(size=(50, 32))
        matches = NearestNeighborMatcher(0.8).match(self._features(query), self._features(ref))
        assert len(matches) == 50
        assert np.array_equal(matches[:, 1], perm[matches[:, 0]])

        # two identical reference descriptors: the ratio test drops the ambiguous query
        ref_dup = np.vstack([ref, ref[:1]])
        m = NearestNeighborMatcher(0.8).match(self._features(ref[:1]), self._features(ref_dup))
        assert len(m) == 0

    def test_min_similarity_drops_distinct_but_dissimilar_pairs(self) -> None:
        # orthogonal-ish descriptors are each other's mutual best with a clear margin, yet far
        # apart: the ratio test keeps them, the cosine floor does not
        rng = np.random.default_rng(1)
        ref = rng.normal(size=(40, 64))
        near = ref[:20] + 0.05 * rng.normal(size=(20, 64))
        far = ref[20:] + 1.2 * rng.normal(size=(20, 64))
        query = self._features(np.vstack([near, far]))
        loose = NearestNeighborMatcher(0.95).match(query, self._features(ref))
        floored = NearestNeighborMatcher(0.95, 0.82).match(query, self._features(ref))
        assert (loose[:, 0] >= 20).sum() > 0  # some far pairs pass the ratio test alone
        assert set(floored[:, 0]) == set(range(20))
        assert np.array_equal(floored[:, 1], floored[:, 0])
        with pytest.raises(ValueError, match="min_similarity"):
            NearestNeighborMatcher(0.95, 1.0)

    def test_too_few_keypoints(self) -> None:
        one = self._features(np.ones((1, 4)))
        assert NearestNeighborMatcher().match(one, one).shape == (0, 2)

    def test_match_many_stops_when_asked(self) -> None:
        features = self._features(np.random.default_rng(2).normal(size=(20, 8)))
        matcher = NearestNeighborMatcher()
        asked = []

        def stop_after_two() -> bool:
            asked.append(True)
            return len(asked) > 2

        matched = matcher.match_many(features, [features] * 4, stop=stop_after_two)
        assert len(matched) == 2
        assert len(matcher.match_many(features, [features] * 4)) == 4


class TestThumbnail:
    def test_large_image_is_averaged_down_before_the_blur(
        self, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        """Issue 14: blurring a 6300×6300 upload in full took 6 s per add; the blur now runs
        at 640 pixels wide, and the descriptor is the same as the 640-pixel image's."""
        rng = np.random.default_rng(0)
        small = cv2.resize(
            rng.integers(0, 255, (24, 32, 3), dtype=np.uint8), (640, 480), cv2.INTER_CUBIC
        )
        large = cv2.resize(small, (3200, 2400), interpolation=cv2.INTER_CUBIC)
        blurred: list[tuple[int, ...]] = []
        real_blur = cv2.GaussianBlur

        def recording_blur(image: np.ndarray, *args: object) -> np.ndarray:
            blurred.append(image.shape)
            return real_blur(image, *args)  # type: ignore[call-overload, no-any-return]

        monkeypatch.setattr(cv2, "GaussianBlur", recording_blur)
        descriptor = ThumbnailDescriptor()
        no_features = LocalFeatures(
            np.zeros((0, 2), np.float32), np.zeros((0, 8), np.float32), np.zeros(0), (0, 0)
        )
        a = descriptor.compute(small, no_features)
        b = descriptor.compute(large, no_features)
        assert blurred == [(480, 640), (480, 640)]
        assert float(a @ b) > 0.999
