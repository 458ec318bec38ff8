"""Sub-pixel matches: each reference keypoint moved to where the patch around its query
keypoint aligns in the reference image (pyramidal Lucas-Kanade, OpenCV's
``calcOpticalFlowPyrLK``), on images at up to twice the resolution the keypoints were found at.

Keypoints found on a shrunken image (XFeat at 640 px) sit on that image's pixel grid: on a
1226 px frame they are off by a pixel or two, which the structureless estimators turn into
centimetres. Only the reference side moves, so a query keypoint matched in several references
stays one point and the references' keypoints all align to it. A keypoint whose refinement
fails, or moves further than ``MAX_SHIFT_PX``, keeps its matched position.

The two images of a pair may differ in size (a portrait query against landscape references,
another camera's resolution): both are aligned on a common canvas, padded at the right and
bottom, so that pixel coordinates stay as they are. Their patches must be of one scale, so a
pair is aligned at the detail of the coarser image (refinement pixels per pixel the keypoints
were found at: a 640 px reference holds half a 1920 px query's at 1280 px), the other shrunk to
it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from services.estimators.base import ReferenceObservation
from services.runtime.spare_workers import Spread
from services.types import FloatArray, UInt8Array

WINDOW_PX = 11  # the aligned patch's side, in pixels of the refinement images
PYRAMID_LEVELS = 2
MAX_SHIFT_PX = 8.0  # in pixels of the refinement images
# how many times the extraction's longer side the images are refined at (at most their own)
RESOLUTION_FACTOR = 2
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.01)
# how far apart (relative) the two images' detail may be before the finer one is shrunk: an
# 11 px patch then differs by at most a pixel across
DETAIL_TOLERANCE = 0.1


@dataclass(frozen=True)
class RefinementImage:
    """A greyscale image at the refinement's resolution, the size of the full image its
    keypoints are given in (a keypoint's COLMAP pixel coordinates times ``shape / full``
    are the same point here) and the longer side it was asked at (``refinement_side`` of the
    extraction's)."""

    gray: UInt8Array
    full_width: int
    full_height: int
    side: int

    @property
    def scale(self) -> tuple[float, float]:
        """(x, y): refinement pixels per full-size pixel."""
        height, width = self.gray.shape
        return width / self.full_width, height / self.full_height

    @property
    def detail(self) -> float:
        """Refinement pixels per pixel of the image the keypoints were found on (the full
        image at ``side / RESOLUTION_FACTOR``, never enlarged)."""
        longer = max(self.full_width, self.full_height)
        extraction = min(1.0, self.side / RESOLUTION_FACTOR / longer)
        return float(max(self.gray.shape) / longer / extraction)

    @property
    def nbytes(self) -> int:
        return int(self.gray.nbytes)


def refinement_side(extraction_side: int) -> int:
    """The longer side images are refined at, for keypoints found at ``extraction_side``."""
    return RESOLUTION_FACTOR * extraction_side


def refinement_image(
    rgb: UInt8Array, full_width: int, full_height: int, side: int
) -> RefinementImage:
    """``rgb`` ((H, W, 3) uint8, an image of ``full_width`` × ``full_height`` possibly decoded
    reduced) in grey, shrunk (area averaging) so that its longer side is at most ``side``
    (never enlarged)."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb
    longer = max(full_width, full_height)
    shrunk = min(side, max(gray.shape))
    if longer > shrunk:
        width = max(1, round(full_width * shrunk / longer))
        height = max(1, round(full_height * shrunk / longer))
        if (height, width) != gray.shape:
            gray = cv2.resize(gray, (width, height), interpolation=cv2.INTER_AREA)
    return RefinementImage(np.ascontiguousarray(gray), full_width, full_height, side)


def refine_reference_keypoints(
    query: RefinementImage,
    observations: Sequence[ReferenceObservation],
    reference_image: Callable[[str], RefinementImage | None],
    stop: Callable[[], bool] = lambda: False,
    query_points: Callable[[FloatArray], FloatArray] | None = None,
    spread: Spread | None = None,
) -> list[ReferenceObservation]:
    """``observations`` with their reference keypoints refined on ``query``'s patches;
    ``reference_image(image_id)`` gives a reference's image (None: its matches stay as they
    are). ``query_points`` maps the observations' query keypoints into ``query``'s full image
    (None: they are in it already; e.g. the upload's keypoints into the upload turned
    upright). Refinement stops at the first reference reached once ``stop()`` is true; the
    rest keep their matched positions. ``spread``: runs the references in parallel runs (None:
    one after the other)."""

    def refine(run: Sequence[ReferenceObservation]) -> list[ReferenceObservation]:
        refined = []
        query_at: dict[float, RefinementImage] = {}  # the query shrunk, by detail
        for observation in run:
            image = (
                None
                if stop() or observation.num_matches == 0
                else reference_image(observation.image_id)
            )
            if image is None:
                refined.append(observation)
                continue
            query_xy = (
                observation.query_xy if query_points is None else query_points(observation.query_xy)
            )
            detail = min(query.detail, image.detail)
            if detail not in query_at:
                query_at[detail] = _at_detail(query, detail)
            refined.append(
                _refine(query_at[detail], query_xy, observation, _at_detail(image, detail))
            )
        return refined

    return spread(refine, observations) if spread is not None else refine(observations)


def _at_detail(image: RefinementImage, detail: float) -> RefinementImage:
    """``image`` shrunk (area averaging) to ``detail``; itself when it is within
    ``DETAIL_TOLERANCE`` of it or coarser."""
    if image.detail <= detail * (1.0 + DETAIL_TOLERANCE):
        return image
    factor = detail / image.detail
    height, width = image.gray.shape
    size = (max(1, round(width * factor)), max(1, round(height * factor)))
    gray = np.asarray(cv2.resize(image.gray, size, interpolation=cv2.INTER_AREA), dtype=np.uint8)
    return RefinementImage(gray, image.full_width, image.full_height, image.side)


def _refine(
    query: RefinementImage,
    query_xy: FloatArray,
    observation: ReferenceObservation,
    reference: RefinementImage,
) -> ReferenceObservation:
    query_scale = np.array(query.scale)
    reference_scale = np.array(reference.scale)
    query_gray, reference_gray = _on_one_canvas(query.gray, reference.gray)
    # COLMAP coordinates (top-left pixel centre at (0.5, 0.5)) to OpenCV's (at (0, 0))
    start = (query_xy * query_scale - 0.5).astype(np.float32).reshape(-1, 1, 2)
    guess = (observation.reference_xy * reference_scale - 0.5).astype(np.float32).reshape(-1, 1, 2)
    moved, status, _ = cv2.calcOpticalFlowPyrLK(
        query_gray,
        reference_gray,
        start,
        guess.copy(),
        winSize=(WINDOW_PX, WINDOW_PX),
        maxLevel=PYRAMID_LEVELS,
        criteria=_CRITERIA,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    moved = moved.reshape(-1, 2).astype(np.float64)
    shift = np.linalg.norm(moved - guess.reshape(-1, 2), axis=1)
    ok = (status.ravel() == 1) & np.isfinite(shift) & (shift < MAX_SHIFT_PX)
    if not ok.any():
        return observation
    reference_xy = observation.reference_xy.copy()
    reference_xy[ok] = (moved[ok] + 0.5) / reference_scale
    return replace(observation, reference_xy=reference_xy)


def _on_one_canvas(first: UInt8Array, second: UInt8Array) -> tuple[UInt8Array, UInt8Array]:
    """Both images at the size of the smallest canvas that holds either (OpenCV's optical flow
    takes two images of one size), padded with black at the right and bottom."""
    height = max(first.shape[0], second.shape[0])
    width = max(first.shape[1], second.shape[1])

    def padded(gray: UInt8Array) -> UInt8Array:
        bottom, right = height - gray.shape[0], width - gray.shape[1]
        if bottom == 0 and right == 0:
            return gray
        return np.asarray(
            cv2.copyMakeBorder(gray, 0, bottom, 0, right, cv2.BORDER_CONSTANT, value=0),
            dtype=np.uint8,
        )

    return padded(first), padded(second)
