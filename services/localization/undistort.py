"""Matches of distorted cameras (any COLMAP model) moved onto pinhole cameras before the
estimators: every keypoint goes through pycolmap's model of its camera
(``projection.undistort_to_pinhole``), so the estimators, the verification and the
uncertainty see only pinhole cameras, and the answer's masks go back to the matches as made.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from services.estimators.base import EstimateResult, ReferenceObservation
from services.geometry.camera import Camera
from services.geometry.projection import pinhole_of, undistort_to_pinhole
from services.types import BoolArray


@dataclass(frozen=True)
class UndistortedMatches:
    """Attributes:
    camera: the query camera as a pinhole (the given one when it has no distortion).
    references: the observations with undistorted pixels on pinhole cameras, each holding the
        matches whose two keypoints could be undistorted.
    kept: per observation as given, the (M_i,) mask of the matches ``references`` holds.
    """

    camera: Camera
    references: list[ReferenceObservation]
    kept: list[BoolArray]

    def masks_as_given(self, masks: list[BoolArray]) -> list[BoolArray]:
        """Masks over ``references``' matches → masks over the matches as given."""
        out = []
        for kept, mask in zip(self.kept, masks, strict=True):
            full = np.zeros(kept.shape[0], dtype=bool)
            full[kept] = mask
            out.append(full)
        return out

    def result_as_given(self, result: EstimateResult) -> EstimateResult:
        """``result`` with its inlier masks over the matches as given."""
        return replace(result, inliers=self.masks_as_given(result.inliers))


def undistort_matches(camera: Camera, references: list[ReferenceObservation]) -> UndistortedMatches:
    """Undistort the query keypoints of every observation with ``camera`` and its reference
    keypoints with the reference's camera; a match is kept when both keypoints are."""
    query_camera = pinhole_of(camera)
    out: list[ReferenceObservation] = []
    kept: list[BoolArray] = []
    for ref in references:
        if not camera.distorted and not ref.camera.distorted:
            out.append(ref)
            kept.append(np.ones(ref.num_matches, dtype=bool))
            continue
        ref_camera, ref_xy, ok = undistort_to_pinhole(ref.camera, ref.reference_xy)
        _, query_xy, query_ok = undistort_to_pinhole(camera, ref.query_xy)
        ok = ok & query_ok
        out.append(
            replace(
                ref,
                camera=ref_camera,
                reference_xy=ref_xy[ok],
                query_xy=query_xy[ok],
                reference_depth=None if ref.reference_depth is None else ref.reference_depth[ok],
                query_depth=None if ref.query_depth is None else ref.query_depth[ok],
            )
        )
        kept.append(ok)
    return UndistortedMatches(query_camera, out, kept)
