"""Which frames of an aligned session a map takes: those that add a view it lacks.

A capture's frames lie a centimetre or two apart; a map's references are spread wider. Added
all, a session makes one stretch of the map ten times denser than the rest, and a query there
retrieves ten near-copies of one view (little baseline for the structureless estimators).
A session therefore adds its frames at the map's own density: walking the frames in capture
order, a frame is kept unless a reference or an already kept frame lies closer than the map's
spacing (the median distance from a reference to its nearest other reference) while looking
within ``SAME_VIEW_DEG`` of its direction.
"""

from __future__ import annotations

import numpy as np

from services.geometry.rigid import Rigid3d
from services.types import FloatArray

# two cameras whose optical axes are closer than this see the same view
SAME_VIEW_DEG = 15.0
# references whose spacing is measured (a sample of the map's)
SPACING_SAMPLE = 500


def map_spacing(centers: FloatArray) -> float | None:
    """The median distance from a reference (a deterministic sample of at most
    ``SPACING_SAMPLE``) to its nearest other reference; None for fewer than two."""
    centers = np.asarray(centers, np.float64)
    if len(centers) < 2:
        return None
    step = max(len(centers) // SPACING_SAMPLE, 1)
    nearest = []
    for i in range(0, len(centers), step):
        distances = np.linalg.norm(centers - centers[i], axis=1)
        distances[i] = np.inf
        nearest.append(distances.min())
    return float(np.median(nearest))


def _axes(poses: list[Rigid3d]) -> FloatArray:
    """Each camera's optical axis (its +z) in world coordinates."""
    return np.array([pose.rotation[2] for pose in poses]).reshape(-1, 3)


def new_views(frames: list[Rigid3d], references: list[Rigid3d], spacing: float) -> list[int]:
    """Indices of the ``frames`` (``cam_from_map``, capture order) that add a view the
    ``references`` and the frames kept before them lack."""
    centers = np.array([p.center for p in references]).reshape(-1, 3)
    axes = _axes(references)
    cos_same = np.cos(np.radians(SAME_VIEW_DEG))
    kept: list[int] = []
    for i, frame in enumerate(frames):
        near = np.linalg.norm(centers - frame.center, axis=1) < spacing
        axis = frame.rotation[2]
        if not np.any(near & (axes @ axis > cos_same)):
            kept.append(i)
            centers = np.vstack([centers, frame.center])
            axes = np.vstack([axes, axis])
    return kept
