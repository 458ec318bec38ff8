"""LightGlue from the exported ONNX graph, with a cheap first pass that decides which of the
retrieved pairs deserve it.

LightGlue costs ~0.1–0.4 s a pair on two CPU cores (quadratic in the keypoints), mutual
nearest neighbours a few milliseconds. ``match_many`` matches every pair with mutual nearest
neighbours first and runs LightGlue on the ``lightglue_pairs`` pairs with the most of them;
the other pairs keep their nearest-neighbour matches (``None`` runs LightGlue on all).
``lightglue_keypoints`` caps the keypoints LightGlue sees per image: extractors return them
best first, so it takes the leading ones (LightGlue's attention is quadratic in them; 512
instead of 1024 is ~3x faster a pair).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from services.features.base import LocalFeatures
from services.matching.base import match_each
from services.matching.nearest_neighbor import NearestNeighborMatcher
from services.runtime.spare_workers import Spread
from services.types import IntArray

_NO_MATCHES = np.zeros((0, 2), dtype=np.int64)


class OnnxLightGlueMatcher:
    def __init__(
        self,
        session: Any,
        model_name: str,
        lightglue_pairs: int | None = None,
        first_pass: NearestNeighborMatcher | None = None,
        lightglue_keypoints: int | None = None,
    ) -> None:
        if lightglue_pairs is not None and lightglue_pairs < 0:
            raise ValueError(f"lightglue_pairs must be >= 0 or None, got {lightglue_pairs}")
        if lightglue_keypoints is not None and lightglue_keypoints < 2:
            raise ValueError(f"lightglue_keypoints must be >= 2 or None, got {lightglue_keypoints}")
        self.session = session
        self.lightglue_pairs = lightglue_pairs
        self.lightglue_keypoints = lightglue_keypoints
        self.first_pass = first_pass or NearestNeighborMatcher(ratio=0.95)
        budget = "all" if lightglue_pairs is None else f"top{lightglue_pairs}"
        cap = "" if lightglue_keypoints is None else f"-{lightglue_keypoints}kp"
        self.name = f"{model_name}{cap}-{budget}+{self.first_pass.name}"

    def match(self, query: LocalFeatures, reference: LocalFeatures) -> IntArray:
        """(K, 2) query/reference keypoint indices; only the first ``lightglue_keypoints``
        keypoints of each image can match."""
        if len(query) < 2 or len(reference) < 2:
            return _NO_MATCHES
        cap = self.lightglue_keypoints
        feeds = {
            # the graph's pixel centres are at integers, COLMAP's at +0.5
            "keypoints0": (query.keypoints[:cap] - 0.5)[None].astype(np.float32),
            "keypoints1": (reference.keypoints[:cap] - 0.5)[None].astype(np.float32),
            "descriptors0": query.descriptors[:cap][None].astype(np.float32),
            "descriptors1": reference.descriptors[:cap][None].astype(np.float32),
            "image_size0": np.array([query.image_size], np.float32),
            "image_size1": np.array([reference.image_size], np.float32),
        }
        (matches0,) = self.session.run(["matches0"], feeds)
        rows = np.flatnonzero(matches0[0] >= 0)
        return np.stack([rows, matches0[0][rows]], axis=1).astype(np.int64)

    def match_many(
        self,
        query: LocalFeatures,
        references: Sequence[LocalFeatures],
        stop: Callable[[], bool] | None = None,
        spread: Spread | None = None,
    ) -> list[IntArray]:
        if self.lightglue_pairs is None:
            return match_each(self.match, query, references, stop, spread)
        out = self.first_pass.match_many(query, references, stop, spread)
        ranked = np.argsort([-len(m) for m in out], kind="stable")
        best = [int(i) for i in ranked[: self.lightglue_pairs]]
        refined = match_each(self.match, query, [references[i] for i in best], stop, spread)
        for i, matches in zip(best, refined, strict=False):  # fewer when stopped
            out[i] = matches
        return out
