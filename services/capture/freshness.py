"""Whether a map's references still show what is there: votes from the frames of a capture
session that the map localized.

A frame the map localized confidently shows the place as it is now, at a known pose. The
references that cover it — their centre within ``COVER_SPACINGS`` × the map's spacing of the
frame's and their optical axis within ``COVER_DEG`` of its — should match it about as well as
the references its localization retrieved did. Each covering reference gets a vote: its matches
to the frame that agree with the two known poses (within ``EPIPOLAR_PX`` of their epipolar
lines) are counted; fewer than ``STALE_FRACTION`` of the best retrieved reference's inliers
(and fewer than ``STALE_INLIERS``) is a **stale** vote, otherwise a **fresh** one. A frame
whose best retrieved reference has fewer than ``MIN_EVIDENCE`` inliers casts no vote: the
place matched too weakly to tell. A reference is stale when its votes in a session are all
stale.

A covering reference that the frame's localization retrieved votes fresh from the inliers it
gave there when they are enough; the others, and any vote that would be stale, are matched
with the frame's features, so a stale vote always counts every match.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from services.features.base import LocalFeatures
from services.geometry.camera import Camera
from services.geometry.epipolar import epipolar_errors
from services.geometry.rigid import Rigid3d
from services.localization.answer import LocalizationResult, RetrievedReference
from services.matching.base import Matcher
from services.references.store import ReferenceView
from services.types import Float32Array, FloatArray, IntArray

COVER_SPACINGS = 2.0
COVER_DEG = 30.0
# the covering references of a frame that vote (the nearest)
MAX_COVERING = 8
EPIPOLAR_PX = 4.0
STALE_FRACTION = 0.1
STALE_INLIERS = 15
MIN_EVIDENCE = 50


@dataclass(frozen=True)
class Vote:
    """A covering reference's vote from one frame: its inliers against the frame and the
    best retrieved reference's (the level it is compared with)."""

    image_id: str
    frame: str
    inliers: int
    expected: int

    @property
    def stale(self) -> bool:
        return self.inliers < min(STALE_INLIERS, STALE_FRACTION * self.expected)


def covering(
    frame: Rigid3d, references: list[Rigid3d], spacing: float, limit: int = MAX_COVERING
) -> list[int]:
    """Indices of the ``references`` (``cam_from_map``) that cover ``frame``: within
    ``COVER_SPACINGS`` × ``spacing`` of its centre, looking within ``COVER_DEG`` of its
    direction; the nearest ``limit``, nearest first."""
    if not references:
        return []
    centers = np.array([r.center for r in references])
    axes = np.array([r.rotation[2] for r in references])
    distance = np.linalg.norm(centers - frame.center, axis=1)
    near = (distance <= COVER_SPACINGS * spacing) & (
        axes @ frame.rotation[2] >= np.cos(np.radians(COVER_DEG))
    )
    found = np.flatnonzero(near)
    return [int(i) for i in found[np.argsort(distance[found])][:limit]]


def agreeing_matches(
    frame_camera: Camera,
    frame_pose: Rigid3d,
    frame_xy: FloatArray | Float32Array,
    reference_camera: Camera,
    reference_pose: Rigid3d,
    reference_xy: FloatArray | Float32Array,
    matches: IntArray,
) -> int:
    """How many ``matches`` ((M, 2) frame/reference keypoint indices) lie within
    ``EPIPOLAR_PX`` of the epipolar lines the two poses give."""
    if len(matches) == 0:
        return 0
    errors = epipolar_errors(
        frame_camera,
        frame_pose,
        np.asarray(frame_xy, np.float64)[matches[:, 0]],
        reference_camera,
        reference_pose,
        np.asarray(reference_xy, np.float64)[matches[:, 1]],
    )
    return int(np.count_nonzero(errors <= EPIPOLAR_PX))


def best_inliers(result: LocalizationResult) -> int:
    """How well a frame's place matched: its best retrieved reference's inliers (the level
    its votes are compared with, and ``MIN_EVIDENCE``'s)."""
    return max((r.num_inliers for r in result.retrieved), default=0)


def reusable_inliers(result: LocalizationResult, camera: Camera) -> dict[str, RetrievedReference]:
    """The retrieved references of a frame's localization (``result``) by image id, whose
    inlier pixels are the frame's as given: localized with its own ``camera``, upright (none
    otherwise)."""
    if result.camera != camera or result.upright_turn_deg != 0:
        return {}
    return {r.image_id: r for r in result.retrieved}


def frame_votes(
    frame: str,
    camera: Camera,
    cam_from_map: Rigid3d,
    references: Sequence[ReferenceView],
    inliers: Mapping[str, RetrievedReference],
    describe: Callable[[], LocalFeatures | None],
    matcher: Matcher,
    expected: int,
) -> list[Vote]:
    """The votes of ``frame`` (its ``camera`` at ``cam_from_map``) on the ``references`` that
    cover it, against ``expected`` (its best retrieved reference's inliers). A reference in
    ``inliers`` (``reusable_inliers``) whose inliers agree enough votes fresh with them; the
    others are matched with the frame's features, ``describe()``d once at most (None: they
    cast no vote)."""
    votes = []
    features: LocalFeatures | None = None
    described = False
    for reference in references:
        retrieved = inliers.get(reference.image_id)
        if retrieved is not None:
            pairs = np.repeat(np.arange(len(retrieved.query_xy))[:, None], 2, axis=1)
            agreeing = agreeing_matches(
                camera,
                cam_from_map,
                retrieved.query_xy,
                reference.camera,
                reference.cam_from_world,
                retrieved.reference_xy,
                pairs,
            )
            vote = Vote(reference.image_id, frame, agreeing, expected)
            if not vote.stale:
                votes.append(vote)
                continue
        if not described:
            features, described = describe(), True
        if features is None:
            continue
        agreeing = agreeing_matches(
            camera,
            cam_from_map,
            features.keypoints,
            reference.camera,
            reference.cam_from_world,
            reference.features.keypoints,
            matcher.match(features, reference.features),
        )
        votes.append(Vote(reference.image_id, frame, agreeing, expected))
    return votes


def stale_references(votes: list[Vote]) -> dict[str, list[Vote]]:
    """The references whose votes are all stale, with their votes; and (as an empty list)
    those with a fresh vote."""
    by_reference: dict[str, list[Vote]] = {}
    for vote in votes:
        by_reference.setdefault(vote.image_id, []).append(vote)
    return {
        image_id: (theirs if all(v.stale for v in theirs) else [])
        for image_id, theirs in by_reference.items()
    }
