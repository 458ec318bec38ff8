"""The stages every localizer composes, one frame at a time: decode (the camera checked
against the image), extract (features in full-size pixels), retrieve (encode, then search the
map's index) and match (pairs of keypoints become a reference's correspondences)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from services.errors import ImageTooLargeError, InvalidInputError
from services.estimators.base import ReferenceObservation
from services.features.base import FeatureExtractor, LocalFeatures
from services.geometry.camera import Camera
from services.imaging.decode import (
    DecodedImage,
    decode_depth,
    decode_image_reduced,
    image_size_from_header,
)
from services.matching.base import Matcher
from services.references.store import ReferenceView
from services.retrieval.base import GlobalDescriptor
from services.retrieval.contracts import RetrievalIndex
from services.retrieval.search import PositionPrior
from services.retrieval.thinning import search_thinned
from services.retrieval.vlad import encode
from services.runtime.spare_workers import Spread
from services.types import Float32Array, FloatArray, IntArray, UInt8Array

# a retrieved reference: its image id and retrieval score
Retrieved = tuple[str, float]


# --- decode ---


def check_camera_matches(camera: Camera, image: DecodedImage) -> None:
    """
    Raises:
        InvalidInputError: ``camera`` is not the size of ``image``.
    """
    width, height = image.width, image.height
    if (camera.width, camera.height) != (width, height):
        raise InvalidInputError(
            f"camera is {camera.width}×{camera.height} but the image is {width}×{height}"
        )


def decode_depth_for(
    depth_bytes: bytes | None, camera: Camera, max_pixels: int
) -> Float32Array | None:
    """The depth map of an image seen by ``camera`` (None without one)."""
    if depth_bytes is None:
        return None
    return decode_depth(depth_bytes, camera.width, camera.height, max_pixels)


def decode_frames(images: list[bytes], max_pixels: int, min_side: int) -> list[DecodedImage]:
    """Decode every frame, refusing more than ``max_pixels`` pixels in all (from the headers,
    before any decoding); JPEGs reduced while their longer side stays at least ``min_side``.

    Raises:
        ImageTooLargeError: the frames together are too large.
        ImageDecodeError: a frame is not a decodable JPEG or PNG.
    """
    sizes = [image_size_from_header(data) for data in images]
    total = sum(w * h for w, h in sizes)
    if total > max_pixels:
        raise ImageTooLargeError(
            f"the {len(images)} frames have {total} pixels together; the limit is {max_pixels}"
        )
    return [decode_image_reduced(data, max_pixels, min_side) for data in images]


# --- extract ---


def extract_full_size(extractor: FeatureExtractor, image: DecodedImage) -> LocalFeatures:
    """Features of a (possibly reduced) decoded image in its full-size pixels."""
    return extractor.extract(image.rgb).at_full_size(image.factor, (image.width, image.height))


# --- retrieve ---


def retrieve(
    index: RetrievalIndex,
    global_descriptor: GlobalDescriptor,
    image: UInt8Array,
    query: LocalFeatures,
    top_k: int,
    prior: PositionPrior | None,
    spacing_factor: float | None = None,
) -> list[Retrieved]:
    """The ``top_k`` references of the query (``image`` and its features ``query``), best
    first: encoded by the map's VLAD vocabulary when it has one, else by
    ``global_descriptor``, then searched (thinned at ``spacing_factor``, None: the rule of
    ``search_thinned``; near ``prior`` when given)."""
    query_global = (
        encode(query.descriptors, index.vocabulary)
        if index.vocabulary is not None
        else global_descriptor.compute(image, query)
    )
    rows, scores = search_thinned(index, query_global, top_k, prior, spacing_factor)
    return [(index.image_ids[i], float(s)) for i, s in zip(rows, scores, strict=True)]


# --- match ---


def match(
    matcher: Matcher,
    query: LocalFeatures,
    references: Sequence[tuple[ReferenceView, float]],
    stop: Callable[[], bool],
    spread: Spread | None = None,
    observed: LocalFeatures | None = None,
    query_depth: Float32Array | None = None,
) -> list[ReferenceObservation]:
    """Match ``query`` with each of ``references`` (with its retrieval score) until ``stop``:
    the correspondences of the references reached, in order. ``observed``: the query's
    keypoints where the pose is estimated, one for one with ``query``'s (None: ``query``'s);
    ``query_depth``: the query's depth map there."""
    pairs = matcher.match_many(
        query, [ref.features for ref, _ in references], stop=stop, spread=spread
    )
    # a stopped matcher returns fewer pairs: the references it did not reach drop out
    return [
        observe(observed or query, query_depth, ref, score, ref_pairs)
        for (ref, score), ref_pairs in zip(references, pairs, strict=False)
    ]


class MatchedQuery(NamedTuple):
    """A query described, its references retrieved and matched (at the clockwise ``turn`` of
    the upload, keypoints back in the upload): what every estimator takes. ``names``: the
    matched references' names by image id; ``features``: the query's, in the turned image."""

    camera: Camera
    observations: list[ReferenceObservation]
    names: dict[str, str]
    turn: int
    features: LocalFeatures

    @property
    def num_matches(self) -> int:
        return sum(len(o.query_xy) for o in self.observations)


def observe(
    query: LocalFeatures,
    query_depth: Float32Array | None,
    ref: ReferenceView,
    score: float,
    pairs: IntArray,
) -> ReferenceObservation:
    """The correspondences of ``pairs`` ((M, 2) query/reference keypoint indices)."""
    query_xy = query.keypoints[pairs[:, 0]].astype(np.float64)
    reference_xy = ref.features.keypoints[pairs[:, 1]].astype(np.float64)
    return ReferenceObservation(
        image_id=ref.image_id,
        camera=ref.camera,
        cam_from_world=ref.cam_from_world,
        query_xy=query_xy,
        reference_xy=reference_xy,
        retrieval_score=score,
        reference_depth=_sample_depth(ref.depth, reference_xy),
        query_depth=_sample_depth(query_depth, query_xy),
    )


def _sample_depth(depth: Float32Array | None, xy: FloatArray) -> FloatArray | None:
    """Depth at (M, 2) COLMAP pixel coordinates (nearest pixel); None without a depth map."""
    if depth is None:
        return None
    h, w = depth.shape
    cols = np.clip(np.floor(xy[:, 0]).astype(np.int64), 0, w - 1)
    rows = np.clip(np.floor(xy[:, 1]).astype(np.int64), 0, h - 1)
    return depth[rows, cols].astype(np.float64)
