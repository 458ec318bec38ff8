"""A session's frames placed in the map: its alignment, corrected for the drift of its poses
between the frames the map localized.

Device tracking drifts slowly along the path: one transform cannot place every frame of a long
session to the map's accuracy. Each agreeing checked frame (an anchor) measures the correction
its aligned pose needs: a translation of its centre and a rotation about it. A frame between
two anchors takes their corrections interpolated by its distance along the session's path
(linearly for the translation, spherically for the rotation); a frame before the first or past
the last anchor takes that anchor's. The anchors' own poses become the map's answers for them.

Past the anchors nothing measures the drift: a frame is placed only within ``REACH_M`` of an
anchor along the path, where a drift of ``DRIFT_FRACTION`` of the distance stays within the
alignment's least tolerance. A session that leaves the map extends it by that much; the next
session, checked against the grown map, extends it further.
"""

from __future__ import annotations

import numpy as np

from services.capture.alignment import DRIFT_FRACTION, MIN_TOLERANCE_M, Similarity
from services.geometry.rigid import Rigid3d, matrix_to_quaternion, quaternion_to_matrix
from services.types import FloatArray

# how far along the path from an anchor a frame is placed (map units): a drift of
# DRIFT_FRACTION of the distance reaches MIN_TOLERANCE_M there
REACH_M = MIN_TOLERANCE_M / DRIFT_FRACTION


def slerp(q0: FloatArray, q1: FloatArray, t: float) -> FloatArray:
    """Spherical interpolation between unit quaternions ``[w, x, y, z]`` (the short way)."""
    q0 = np.asarray(q0, np.float64)
    q1 = np.asarray(q1, np.float64)
    dot = float(q0 @ q1)
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: linear, then normalised
        q = q0 + t * (q1 - q0)
    else:
        angle = np.arccos(dot)
        q = (np.sin((1 - t) * angle) * q0 + np.sin(t * angle) * q1) / np.sin(angle)
    out: FloatArray = q / np.linalg.norm(q)
    return out


def arc_lengths(cam_from_session: list[Rigid3d]) -> FloatArray:
    """Each frame's distance along the path from the first frame (the frame index where the
    path has no length)."""
    centers = np.array([pose.center for pose in cam_from_session])
    steps = np.linalg.norm(np.diff(centers, axis=0), axis=1) if len(centers) > 1 else []
    s = np.concatenate(([0.0], np.cumsum(steps)))
    if s[-1] <= 0.0:
        return np.arange(len(cam_from_session), dtype=np.float64)
    return s


def corrected_poses(
    similarity: Similarity, cam_from_session: list[Rigid3d], anchors: dict[int, Rigid3d]
) -> tuple[list[Rigid3d], FloatArray]:
    """Every frame's ``cam_from_map``: ``similarity`` applied, then corrected by the drift the
    ``anchors`` (frame index → its pose localized in the map) measure. Also returns each
    anchor's correction of its centre (map units), in index order."""
    aligned = [similarity.cam_from_map(pose) for pose in cam_from_session]
    if not anchors:
        return aligned, np.zeros(0)
    order = sorted(anchors)
    s = arc_lengths(cam_from_session)
    s_anchor = s[order]
    shift = np.array([anchors[i].center - aligned[i].center for i in order])
    # the world-frame rotation taking an aligned camera's orientation to the anchor's
    turn = np.array(
        [matrix_to_quaternion(anchors[i].rotation.T @ aligned[i].rotation) for i in order]
    )
    out = []
    for k, pose in enumerate(aligned):
        b = int(np.searchsorted(s_anchor, s[k]))
        t = 0.0
        if b == 0:  # before the first anchor
            a = 0
        elif b == len(order):  # past the last
            a = b = len(order) - 1
        else:
            a = b - 1
            span = s_anchor[b] - s_anchor[a]
            t = float((s[k] - s_anchor[a]) / span) if span > 0 else 0.0
        center = pose.center + (1 - t) * shift[a] + t * shift[b]
        world_turn = quaternion_to_matrix(slerp(turn[a], turn[b], t))
        rotation = pose.rotation @ world_turn.T
        out.append(Rigid3d(rotation, -rotation @ center))
    return out, np.linalg.norm(shift, axis=1)


def anchored(cam_from_session: list[Rigid3d], anchors: list[int], reach: float) -> list[int]:
    """Indices of the frames within ``reach`` (session units) of an anchor along the path:
    past it, the drift no anchor measured may exceed what the map tolerates."""
    if not anchors:
        return []
    s = arc_lengths(cam_from_session)
    s_anchor = np.sort(s[anchors])
    nearest = np.abs(s[:, None] - s_anchor[None, :]).min(axis=1)
    return [int(i) for i in np.flatnonzero(nearest <= reach)]
