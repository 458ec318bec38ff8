"""Where a map is weak, on its ground plane: cells of the plane its camera centres span, each
with its references and what the map's self-evaluation measured of those held out there.

The ground plane is the one the centres spread over most (the two leading principal axes of
the centres; a handheld map's lies near eye height, a drive's along the road). A cell is
**weak** when at least half of the references held out in it failed — not localized, or off
by more than ``WRONG_M`` or ``WRONG_DEG`` — or when it holds a single reference (a query there
has one view to lean on).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.types import FloatArray

WRONG_M = 0.25
WRONG_DEG = 5.0
# the default cell: this many times the map's spacing
CELL_SPACINGS = 4.0
# the fewest queries whose failures make a cell weak
MIN_QUERIES = 5


@dataclass(frozen=True)
class HeldOut:
    """A reference held out by a self-evaluation, by its index among the map's references."""

    index: int
    localized: bool
    position_error_m: float
    rotation_error_deg: float

    @property
    def failed(self) -> bool:
        return (
            not self.localized
            or not self.position_error_m <= WRONG_M
            or not self.rotation_error_deg <= WRONG_DEG
        )


@dataclass
class Cell:
    """One cell of the ground plane: its indices along the plane's axes (cell (0, 0) is
    centred on the origin), its centre (map coordinates, at the mean height of its
    references), and what it holds."""

    i: int
    j: int
    center: FloatArray
    references: int = 0
    held_out: int = 0
    failed: int = 0
    errors_m: list[float] = field(default_factory=list)
    queries_localized: int = 0
    queries_failed: int = 0

    @property
    def median_error_m(self) -> float | None:
        return float(np.median(self.errors_m)) if self.errors_m else None

    @property
    def why_weak(self) -> list[str]:
        why = []
        if self.held_out and 2 * self.failed >= self.held_out:
            why.append(f"{self.failed} of {self.held_out} references held out failed")
        queries = self.queries_localized + self.queries_failed
        if queries >= MIN_QUERIES and 2 * self.queries_failed >= queries:
            why.append(f"{self.queries_failed} of {queries} queries failed")
        if self.references == 1:
            why.append("a single reference")
        return why


@dataclass(frozen=True)
class Coverage:
    """The ground plane (``origin`` and the unit axes ``u``, ``v``), the cell size and the
    cells that hold references, in (i, j) order."""

    origin: FloatArray
    u: FloatArray
    v: FloatArray
    cell_m: float
    cells: list[Cell]


def ground_plane(centers: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(origin, u, v): the centres' mean and their two leading principal axes, each signed so
    that its largest component is positive (the same map gives the same plane)."""
    centers = np.asarray(centers, np.float64)
    origin = centers.mean(axis=0)
    if len(centers) < 2:
        return origin, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    _, _, vt = np.linalg.svd(centers - origin, full_matrices=True)
    u, v = (axis * np.sign(axis[np.argmax(np.abs(axis))]) for axis in vt[:2])
    return origin, u, v


def coverage(
    centers: FloatArray,
    held_out: list[HeldOut],
    cell_m: float,
    queries: dict[int, tuple[int, int]] | None = None,
) -> Coverage:
    """The cells of the references' ``centers`` ((N, 3)) at ``cell_m``, with the held-out
    answers of the references in each and ``queries``: the (localized, failed) counts of the
    queries whose best retrieved reference each was, by the reference's index."""
    centers = np.asarray(centers, np.float64).reshape(-1, 3)
    origin, u, v = ground_plane(centers) if len(centers) else (np.zeros(3), *np.eye(3)[:2])
    if not len(centers):
        return Coverage(origin, u, v, cell_m, [])
    offsets = centers - origin
    # cells centred on the origin: (0, 0) is the cell around the centres' mean
    ij = np.floor(np.stack([offsets @ u, offsets @ v], axis=1) / cell_m + 0.5).astype(np.int64)
    cells: dict[tuple[int, int], Cell] = {}
    members: dict[tuple[int, int], list[int]] = {}
    for k, (i, j) in enumerate(ij):
        members.setdefault((int(i), int(j)), []).append(k)
    for (i, j), indices in members.items():
        height = float((offsets[indices] @ np.cross(u, v)).mean())
        center = origin + (i * u + j * v) * cell_m + height * np.cross(u, v)
        cells[(i, j)] = Cell(i, j, center, references=len(indices))
    for answer in held_out:
        cell = cells[(int(ij[answer.index][0]), int(ij[answer.index][1]))]
        cell.held_out += 1
        cell.failed += int(answer.failed)
        if answer.localized and np.isfinite(answer.position_error_m):
            cell.errors_m.append(answer.position_error_m)
    for index, (localized, failed) in (queries or {}).items():
        cell = cells[(int(ij[index][0]), int(ij[index][1]))]
        cell.queries_localized += localized
        cell.queries_failed += failed
    return Coverage(origin, u, v, cell_m, [cells[key] for key in sorted(cells)])
