"""Align a capture session to a map: ``map_from_session`` from the session's frames that were
localized in the map, and the rule that decides whether it is well determined.

Each checked frame ``i`` carries its pose in the session (``cam_from_session``, the device's
tracking) and, when it was localized, its pose in the map (``cam_from_map``) with the answer's
confidence. One frame alone determines a rigid ``map_from_session`` (rotation and
translation); two determine a similarity (the scale from the distance between their centres).
The frames checked are spread evenly over the session in capture order (one in
``CHECK_EVERY``, within [``MIN_CHECKED``, ``MAX_CHECKED``]). The estimate is robust: every
hypothesis from one frame (rigid) or one pair (similarity) is scored by the frames that agree
with it, the best is refined on those frames (least squares over their orientations and
centres) and the agreement measured again.

The rule (:func:`decide`), with ``tolerance = max(MIN_TOLERANCE_M, DRIFT_FRACTION × the
session's path length)``:

- at least ``MIN_AGREEING`` frames localized with confidence ≥ ``MIN_CONFIDENCE``;
- of those, at least ``MIN_AGREEING`` and at least ``MIN_AGREEING_FRACTION`` agree: their
  centre within ``tolerance`` and their rotation within ``MAX_ROTATION_DEG`` of where the
  alignment puts them. Frames that disagree while the map localizes them confidently mean the
  session's poses drifted (or carry a wrong scale) beyond what one transform explains: the
  session is refused, never bent to fit;
- with an unknown scale, the agreeing frames' centres span at least ``MIN_SPAN_TOLERANCES``
  tolerances, so that the scale is determined to a few per cent.

Its uncertainty is read from the agreeing frames' residuals: the RMS of the centre and rotation
residuals, and their standard errors (RMS / √(n − 1)).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from services.geometry.rigid import Rigid3d, rotation_error_deg
from services.types import FloatArray

MIN_CONFIDENCE = 0.8
MIN_AGREEING = 3
MIN_AGREEING_FRACTION = 0.5
MIN_TOLERANCE_M = 0.05
DRIFT_FRACTION = 0.01
MAX_ROTATION_DEG = 2.0
MIN_SPAN_TOLERANCES = 10.0
# a localized frame's typical errors, which weigh its orientation against its centre in the fit
ROTATION_SIGMA_RAD = float(np.radians(0.5))
POSITION_SIGMA_M = 0.02
# frames localized against the map: one in CHECK_EVERY, within [MIN_CHECKED, MAX_CHECKED]
CHECK_EVERY = 10
MIN_CHECKED = 12
MAX_CHECKED = 50
# fewer frames localized than this: the frames around them are checked too, every DENSE_STEP-th
DENSE_BELOW = 6
DENSE_STEP = 2
# pair hypotheses tried for a similarity (every pair up to this many frames)
_MAX_PAIRS = 400
_REFINEMENTS = 3


@dataclass(frozen=True)
class Similarity:
    """``x_map = scale · rotation @ x_session + translation`` (scale 1: rigid)."""

    rotation: FloatArray
    translation: FloatArray
    scale: float = 1.0

    def apply(self, points: FloatArray) -> FloatArray:
        return self.scale * np.asarray(points, np.float64) @ self.rotation.T + self.translation

    def cam_from_map(self, cam_from_session: Rigid3d) -> Rigid3d:
        """A session camera's pose in the map: its centre mapped, its rotation turned."""
        rotation = cam_from_session.rotation @ self.rotation.T
        center = self.apply(cam_from_session.center[None])[0]
        return Rigid3d(rotation, -rotation @ center)

    @classmethod
    def identity(cls) -> Similarity:
        return cls(np.eye(3), np.zeros(3), 1.0)


@dataclass(frozen=True)
class CheckedFrame:
    """A frame localized against the map to align its session: its session pose, and its map
    pose with the answer's confidence (None when it was not localized)."""

    index: int
    cam_from_session: Rigid3d
    cam_from_map: Rigid3d | None
    confidence: float = 0.0


@dataclass(frozen=True)
class Residual:
    """How far the alignment puts a checked frame from where the map localized it."""

    index: int
    position_m: float
    rotation_deg: float
    agrees: bool


@dataclass(frozen=True)
class Alignment:
    """The outcome: ``map_from_session`` (None when refused), the decision's reason (None
    when accepted), the tolerance used, per-frame residuals of the confident frames, and the
    uncertainty read from the agreeing frames."""

    map_from_session: Similarity | None
    reason: str | None
    tolerance_m: float
    residuals: list[Residual]
    confident: int
    agreeing: int
    rms_position_m: float | None = None
    rms_rotation_deg: float | None = None
    position_stderr_m: float | None = None
    rotation_stderr_deg: float | None = None


def path_length(cam_from_session: list[Rigid3d]) -> float:
    """The length of the path through the frames' centres, in capture order."""
    if len(cam_from_session) < 2:
        return 0.0
    centers = np.array([pose.center for pose in cam_from_session])
    return float(np.linalg.norm(np.diff(centers, axis=0), axis=1).sum())


def tolerance_m(path_m: float) -> float:
    """How far an agreeing frame may lie from where the alignment puts it."""
    return max(MIN_TOLERANCE_M, DRIFT_FRACTION * path_m)


def check_count(count: int) -> int:
    """How many of a session's ``count`` frames are localized against the map: one in
    ``CHECK_EVERY``, at least ``MIN_CHECKED`` and at most ``MAX_CHECKED``."""
    return min(max(-(-count // CHECK_EVERY), MIN_CHECKED), MAX_CHECKED)


def check_indices(count: int, wanted: int) -> list[int]:
    """``wanted`` frame indices spread evenly over a session of ``count`` frames in capture
    order, its first and last included (drift grows along the path)."""
    if count <= wanted:
        return list(range(count))
    return sorted({round(float(v)) for v in np.linspace(0, count - 1, wanted)})


def densify(checked: list[int], localized: list[int], count: int) -> list[int]:
    """More frames to check when few of the ``checked`` were ``localized`` (fewer than
    ``DENSE_BELOW``, at least one): every ``DENSE_STEP``-th frame between each localized frame
    and its checked neighbours, not checked yet, at most ``MAX_CHECKED`` in all. A session that
    extends the map overlaps it over a short stretch only."""
    if not localized or len(localized) >= DENSE_BELOW:
        return []
    ordered = sorted(checked)
    wanted: list[int] = []
    for index in localized:
        k = ordered.index(index)
        low = ordered[k - 1] if k > 0 else 0
        high = ordered[k + 1] if k + 1 < len(ordered) else count - 1
        wanted += range(low, high + 1, DENSE_STEP)
    taken = set(checked)
    more = sorted({i for i in wanted if i not in taken})
    return more[: max(MAX_CHECKED - len(checked), 0)]


def align(frames: list[CheckedFrame], path_m: float, metric: bool) -> Alignment:
    """``map_from_session`` from the checked frames by the module's rule. ``metric``: the
    session's poses are in metres (rigid); otherwise its scale is estimated (similarity)."""
    tolerance = tolerance_m(path_m)
    confident = [f for f in frames if f.cam_from_map is not None and f.confidence >= MIN_CONFIDENCE]
    if len(confident) < MIN_AGREEING:
        return Alignment(
            None,
            f"too few frames localized in the map: {len(confident)} of {len(frames)} checked "
            f"with confidence ≥ {MIN_CONFIDENCE} (at least {MIN_AGREEING} needed): the session "
            "does not overlap the map, or shows another place",
            tolerance,
            [],
            len(confident),
            0,
        )
    session_centers = np.array([f.cam_from_session.center for f in confident])
    map_centers = np.array([f.cam_from_map.center for f in confident])  # type: ignore[union-attr]
    # each frame's rotation of the session into the map: R_map_from_session = R_cm^T R_cs
    rotations = np.array(
        [
            f.cam_from_map.rotation.T @ f.cam_from_session.rotation  # type: ignore[union-attr]
            for f in confident
        ]
    )
    best: tuple[int, Similarity] | None = None
    for hypothesis in _hypotheses(rotations, session_centers, map_centers, metric):
        count = int(_agreement(hypothesis, confident, tolerance).sum())
        if best is None or count > best[0]:
            best = (count, hypothesis)
    assert best is not None  # at least MIN_AGREEING confident frames give hypotheses
    similarity = best[1]
    agrees = _agreement(similarity, confident, tolerance)
    for _ in range(_REFINEMENTS):
        if agrees.sum() < 2:
            break
        similarity = _fit(rotations[agrees], session_centers[agrees], map_centers[agrees], metric)
        agrees = _agreement(similarity, confident, tolerance)
    residuals = _residuals(similarity, confident, tolerance)
    agreeing = int(agrees.sum())
    reason = _refusal(
        agreeing, len(confident), similarity, session_centers[agrees], tolerance, metric
    )
    position = np.array([r.position_m for r in residuals if r.agrees])
    rotation = np.array([r.rotation_deg for r in residuals if r.agrees])
    # one frame fits any transform exactly: its residual says nothing
    rms_p = float(np.sqrt(np.mean(position**2))) if len(position) > 1 else None
    rms_r = float(np.sqrt(np.mean(rotation**2))) if len(rotation) > 1 else None
    dof = max(len(position) - 1, 1)
    return Alignment(
        similarity if reason is None else None,
        reason,
        tolerance,
        residuals,
        len(confident),
        agreeing,
        rms_p,
        rms_r,
        rms_p / np.sqrt(dof) if rms_p is not None else None,
        rms_r / np.sqrt(dof) if rms_r is not None else None,
    )


def _refusal(
    agreeing: int,
    confident: int,
    similarity: Similarity,
    agreeing_centers: FloatArray,
    tolerance: float,
    metric: bool,
) -> str | None:
    if agreeing < MIN_AGREEING or agreeing < MIN_AGREEING_FRACTION * confident:
        return (
            f"the session's poses disagree with the map: {agreeing} of {confident} confidently "
            f"localized frames agree with one alignment within {tolerance:.3f} m and "
            f"{MAX_ROTATION_DEG:g}° (at least {MIN_AGREEING} and "
            f"{MIN_AGREEING_FRACTION:.0%} needed): the session drifted"
            + (" or its poses are not in metres" if metric else "")
            + ", or it shows another place"
        )
    if not metric:
        radius = np.linalg.norm(agreeing_centers - agreeing_centers.mean(axis=0), axis=1).max()
        span_m = 2.0 * similarity.scale * float(radius)
        if span_m < MIN_SPAN_TOLERANCES * tolerance:
            return (
                f"the session's scale is not determined: the agreeing frames span {span_m:.3f} m "
                f"in the map, less than {MIN_SPAN_TOLERANCES:g} × {tolerance:.3f} m; capture a "
                "longer path or send metric poses"
            )
    return None


def _hypotheses(
    rotations: FloatArray, session_centers: FloatArray, map_centers: FloatArray, metric: bool
) -> list[Similarity]:
    n = len(rotations)
    if metric:
        return [
            Similarity(r, map_centers[i] - r @ session_centers[i]) for i, r in enumerate(rotations)
        ]
    out = []
    pairs = list(combinations(range(n), 2))
    if len(pairs) > _MAX_PAIRS:
        step = len(pairs) / _MAX_PAIRS
        pairs = [pairs[int(k * step)] for k in range(_MAX_PAIRS)]
    for i, j in pairs:
        d_session = np.linalg.norm(session_centers[i] - session_centers[j])
        if d_session <= 1e-9:
            continue
        out.append(_fit(rotations[[i, j]], session_centers[[i, j]], map_centers[[i, j]], False))
    return out


def _nearest_rotation(matrix: FloatArray) -> FloatArray:
    """The rotation nearest ``matrix`` in the Frobenius norm (a sum of rotations: their
    chordal mean)."""
    u, _, vt = np.linalg.svd(matrix)
    d = np.sign(np.linalg.det(u @ vt))
    mean: FloatArray = u @ np.diag([1.0, 1.0, d]) @ vt
    return mean


def _fit(
    rotations: FloatArray, session_centers: FloatArray, map_centers: FloatArray, metric: bool
) -> Similarity:
    """Least squares over the frames' rotations and centres: the rotation nearest the sum of
    the frames' rotations and the centres' cross-covariance, each weighted by the inverse
    variance of a localized frame's error (``ROTATION_SIGMA_RAD``, ``POSITION_SIGMA_M``: a
    long session's rotation is held mostly by its centres, a short one's by its frames'
    orientations), then the scale and translation of the centres."""
    a = session_centers - session_centers.mean(axis=0)
    b = map_centers - map_centers.mean(axis=0)
    by_rotations = rotations.sum(axis=0) / ROTATION_SIGMA_RAD**2
    rotation = _nearest_rotation(by_rotations)
    scale = 1.0 if metric else _scale(a, b, rotation)
    rotation = _nearest_rotation(by_rotations + scale * (b.T @ a) / POSITION_SIGMA_M**2)
    if not metric:
        scale = _scale(a, b, rotation)
    translation = map_centers.mean(axis=0) - scale * rotation @ session_centers.mean(axis=0)
    return Similarity(rotation, translation, scale)


def _scale(session_offsets: FloatArray, map_offsets: FloatArray, rotation: FloatArray) -> float:
    """The least-squares scale of centred session centres turned by ``rotation`` onto the
    centred map centres (1 where the session's centres coincide)."""
    turned = session_offsets @ rotation.T
    denominator = float((turned * turned).sum())
    if denominator <= 0:
        return 1.0
    return max(float((turned * map_offsets).sum()) / denominator, 1e-12)


def _residuals(
    similarity: Similarity, frames: list[CheckedFrame], tolerance: float
) -> list[Residual]:
    out = []
    for frame in frames:
        predicted = similarity.cam_from_map(frame.cam_from_session)
        assert frame.cam_from_map is not None
        position = float(np.linalg.norm(predicted.center - frame.cam_from_map.center))
        rotation = rotation_error_deg(predicted.rotation, frame.cam_from_map.rotation)
        agrees = position <= tolerance and rotation <= MAX_ROTATION_DEG
        out.append(Residual(frame.index, position, rotation, agrees))
    return out


def _agreement(similarity: Similarity, frames: list[CheckedFrame], tolerance: float) -> np.ndarray:
    return np.array([r.agrees for r in _residuals(similarity, frames, tolerance)], dtype=bool)
