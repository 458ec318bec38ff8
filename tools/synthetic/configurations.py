"""Synthetic query–reference correspondences in the configurations that defeat scale from
baselines, with exact ground truth (no images; see ``correspondences`` for the match model):

- ``street``: a street between two building façades, driven forward: the references are frames
  along the lane, the query a frame on the same line (forward motion, references collinear with
  the query and its viewing direction — the E5+1 degeneracy);
- ``pure_rotation``: the query's centre is one reference's centre (that pair has no baseline);
- ``narrow_baseline``: every reference centre within a few centimetres of one point.

Points, noise and outliers follow ``make_correspondences``: one noisy query keypoint per point,
shared by every reference that matches it; outliers pair a real query keypoint with a random
reference pixel.
"""

from __future__ import annotations

import cv2
import numpy as np

from services.estimators.base import ReferenceObservation
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.types import FloatArray
from tools.synthetic.correspondences import (
    SyntheticCorrespondences,
    project_points,
    sample_room_points,
)

CAMERA = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))

# street frame: x right, y down (ground at +CAMERA_HEIGHT), z along the lane
STREET_HALF_WIDTH = 8.0  # façades at x = ±8 m
CAMERA_HEIGHT = 1.5  # ground plane y = 1.5 m below the camera
FACADE_HEIGHT = 12.0
STREET_LENGTH = (-20.0, 80.0)  # z range of the façades and the ground


def _small_rotation(rng: np.random.Generator, max_deg: float) -> FloatArray:
    return np.asarray(cv2.Rodrigues(np.radians(rng.uniform(-max_deg, max_deg, 3)))[0], np.float64)


def sample_street_points(rng: np.random.Generator, count: int) -> FloatArray:
    """(count, 3) points on the two façades and the road surface, uniformly by area."""
    z0, z1 = STREET_LENGTH
    length = z1 - z0
    facade = FACADE_HEIGHT * length
    ground = 2.0 * STREET_HALF_WIDTH * length
    which = rng.choice(3, size=count, p=np.array([facade, facade, ground]) / (2 * facade + ground))
    z = rng.uniform(z0, z1, count)
    side = np.where(which == 0, -STREET_HALF_WIDTH, STREET_HALF_WIDTH)
    x = np.where(which == 2, rng.uniform(-STREET_HALF_WIDTH, STREET_HALF_WIDTH, count), side)
    y = np.where(
        which == 2, CAMERA_HEIGHT, rng.uniform(CAMERA_HEIGHT - FACADE_HEIGHT, CAMERA_HEIGHT, count)
    )
    return np.stack([x, y, z], axis=1)


def correspondences_for_poses(
    rng: np.random.Generator,
    query_pose: Rigid3d,
    reference_poses: list[Rigid3d],
    points: FloatArray,
    matches_per_reference: int = 300,
    noise_px: float = 1.0,
    outlier_ratio: float = 0.3,
    camera: Camera = CAMERA,
) -> SyntheticCorrespondences:
    """Matches between a query and references at the given poses, over the 3D ``points``
    both see (``matches_per_reference`` per reference at most)."""
    q_xy, q_z, q_vis = project_points(camera, query_pose, points)
    points, q_xy, q_z = points[q_vis], q_xy[q_vis], q_z[q_vis]
    q_noisy = q_xy + rng.normal(0.0, noise_px, q_xy.shape)
    references, masks = [], []
    for i, pose in enumerate(reference_poses):
        r_xy, _, r_vis = project_points(camera, pose, points)
        visible = np.flatnonzero(r_vis)
        m = min(matches_per_reference, visible.size)
        chosen = rng.choice(visible, size=m, replace=False)
        num_out = round(outlier_ratio * m)
        is_out = np.zeros(m, dtype=bool)
        is_out[rng.choice(m, size=num_out, replace=False)] = True
        ref_xy = r_xy[chosen] + rng.normal(0.0, noise_px, (m, 2))
        ref_xy[is_out] = rng.uniform([0, 0], [camera.width, camera.height], (num_out, 2))
        query_idx = chosen.copy()
        query_idx[is_out] = rng.choice(points.shape[0], size=num_out)
        references.append(
            ReferenceObservation(
                image_id=f"ref{i:02d}",
                camera=camera,
                cam_from_world=pose,
                query_xy=q_noisy[query_idx],
                reference_xy=ref_xy,
                retrieval_score=float(1.0 - 0.03 * i),
            )
        )
        masks.append(~is_out)
    return SyntheticCorrespondences(camera, query_pose, references, float(np.median(q_z)), masks)


def _looking_along_z(center: FloatArray, rotation: FloatArray) -> Rigid3d:
    return Rigid3d(rotation, -rotation @ center)


def street(
    seed: int,
    num_references: int = 10,
    spacing_m: float = 1.5,
    lateral_jitter_m: float = 0.05,
    max_rotation_deg: float = 1.0,
    matches_per_reference: int = 300,
    noise_px: float = 1.0,
    outlier_ratio: float = 0.3,
) -> SyntheticCorrespondences:
    """Forward motion down a street: references every ``spacing_m`` along the lane (centres
    jittered sideways and vertically by up to ``lateral_jitter_m``, headings by up to
    ``max_rotation_deg``), the query on the same line between two of them, all looking along
    the lane."""
    rng = np.random.default_rng([seed, 15])
    along = spacing_m * np.arange(num_references, dtype=np.float64)
    jitter = rng.uniform(-lateral_jitter_m, lateral_jitter_m, (num_references, 2))
    refs = [
        _looking_along_z(
            np.array([jitter[i, 0], jitter[i, 1], along[i]]), _small_rotation(rng, max_rotation_deg)
        )
        for i in range(num_references)
    ]
    z = rng.uniform(along[1], along[-2])
    q_jitter = rng.uniform(-lateral_jitter_m, lateral_jitter_m, 2)
    query = _looking_along_z(
        np.array([q_jitter[0], q_jitter[1], z]), _small_rotation(rng, max_rotation_deg)
    )
    points = sample_street_points(rng, 30_000)
    return correspondences_for_poses(
        rng, query, refs, points, matches_per_reference, noise_px, outlier_ratio
    )


def _room_references(
    rng: np.random.Generator, center: FloatArray, count: int, spread_m: FloatArray
) -> list[Rigid3d]:
    poses = []
    for _ in range(count):
        c = center + rng.uniform(-spread_m, spread_m)
        poses.append(_looking_along_z(c, _small_rotation(rng, 10.0)))
    return poses


def pure_rotation(seed: int, num_references: int = 6) -> SyntheticCorrespondences:
    """A query in the synthetic room whose centre is the first reference's centre, rotated by
    5–10° from it; the other references spread ±1.5 m around it."""
    rng = np.random.default_rng([seed, 16])
    center = rng.uniform([-1.5, -0.5, -2.0], [1.5, 0.5, 0.0])
    refs = _room_references(rng, center, num_references, np.array([1.5, 0.5, 1.5]))
    refs[0] = _looking_along_z(center, refs[0].rotation)
    axis = rng.normal(size=3)
    angle = np.radians(rng.uniform(5.0, 10.0))
    turn = cv2.Rodrigues(axis / np.linalg.norm(axis) * angle)[0]
    query = _looking_along_z(center, turn @ refs[0].rotation)
    return correspondences_for_poses(rng, query, refs, sample_room_points(rng, 30_000))


def narrow_baseline(
    seed: int, num_references: int = 6, baseline_m: float = 0.02
) -> SyntheticCorrespondences:
    """References in the synthetic room whose centres lie within ±``baseline_m`` of one point,
    the query 1 m away from it."""
    rng = np.random.default_rng([seed, 17])
    center = rng.uniform([-1.5, -0.5, -2.0], [1.5, 0.5, 0.0])
    refs = _room_references(rng, center, num_references, np.full(3, baseline_m))
    offset = rng.normal(size=3)
    q_center = center + offset / np.linalg.norm(offset)
    query = _looking_along_z(q_center, _small_rotation(rng, 8.0))
    return correspondences_for_poses(rng, query, refs, sample_room_points(rng, 30_000))
