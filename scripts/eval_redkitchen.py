"""In-process evaluation of the localization engine on the redkitchen frames (7-Scenes).

Split (the dataset README's suggestion): references = frames 0…499 every 5th (100 images),
queries = frames 500…999 every 10th (50 images). Ground truth poses come from
``poses_c2w.csv`` (camera-to-world 3×4; ``cam_from_world`` is its inverse).

Besides pose recall, the script reports
- the "localizable" subset: queries with a reference within 0.3 m and 15° (from ground truth),
  and the fraction of them localized within 10 cm and 5° (project target: >= 80 %);
- retrieval recall@10 over queries with a reference within 0.5 m and 30°;
- optionally, false accepts of unrelated images (``--unrelated N``), which must be rejected.

Run from the repository root, e.g.::

    PYTHONPATH=. python scripts/eval_redkitchen.py --json out/redkitchen.json
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.estimators.base import EstimatorOptions
from services.estimators.registry import DEFAULT_ESTIMATOR, estimator_names
from services.features.sift import SiftExtractor, SiftOptions
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d, pose_error, rotation_error_deg
from services.matching.nearest_neighbor import NearestNeighborMatcher
from services.pipeline import (
    LocalizationResult,
    LocalizeParams,
    Localizer,
    ReferenceData,
    ReferenceView,
    RetrievalIndex,
)
from services.retrieval.thumbnail import ThumbnailDescriptor
from services.synthetic_scene import encode_png, unrelated_image

DEFAULT_DATASET = Path(__file__).resolve().parents[1] / ".." / "shared" / "datasets" / "redkitchen"
WIDTH, HEIGHT = 640, 480
INTRINSICS = {
    # fx, fy, cx, cy. "colour" fits the colour frames better (dataset README).
    "colour": (525.0, 525.0, 320.0, 240.0),
    "original": (585.0, 585.0, 320.0, 240.0),
}
STAGES = ("decode", "extract", "retrieve", "match", "estimate", "total")
RECALL_THRESHOLDS = ((0.05, 5.0), (0.10, 10.0), (0.25, 2.0))


class InMemoryStore:
    """A ``ReferenceStore`` over references held in a dict (the evaluation's map)."""

    def __init__(self) -> None:
        self._views: dict[str, ReferenceView] = {}
        self._descriptors: dict[str, NDArray[np.float32]] = {}

    def add(
        self, image_id: str, name: str, camera: Camera, pose: Rigid3d, data: ReferenceData
    ) -> None:
        self._views[image_id] = ReferenceView(
            image_id, name, camera, pose, data.features, data.depth
        )
        self._descriptors[image_id] = data.global_descriptor

    def __len__(self) -> int:
        return len(self._views)

    def retrieval_index(self) -> RetrievalIndex:
        ids = list(self._views)
        if not ids:
            return RetrievalIndex([], np.zeros((0, 1), np.float32), np.zeros((0, 3)))
        return RetrievalIndex(
            ids,
            np.stack([self._descriptors[i] for i in ids]),
            np.stack([self._views[i].cam_from_world.center for i in ids]),
        )

    def load_references(self, image_ids: list[str]) -> list[ReferenceView]:
        return [self._views[i] for i in image_ids if i in self._views]

    def poses(self) -> dict[str, Rigid3d]:
        return {i: v.cam_from_world for i, v in self._views.items()}


def load_poses(dataset: Path) -> dict[int, Rigid3d]:
    """Frame index → ``cam_from_world`` from ``poses_c2w.csv`` (camera-to-world rows)."""
    poses: dict[int, Rigid3d] = {}
    with open(dataset / "poses_c2w.csv", newline="") as f:
        for row in csv.DictReader(f):
            frame = int(Path(row["image"]).name.split("-")[1].split(".")[0])
            m = np.array([float(row[f"T_c2w_{r}{c}"]) for r in range(3) for c in range(4)])
            world_from_cam = Rigid3d(m.reshape(3, 4)[:, :3], m.reshape(3, 4)[:, 3])
            # KinectFusion rotations are orthonormal only to ~1e-7; re-orthonormalise.
            u, _, vt = np.linalg.svd(world_from_cam.rotation)
            world_from_cam = Rigid3d(u @ vt, world_from_cam.translation)
            poses[frame] = world_from_cam.inverse()
    return poses


def image_path(dataset: Path, frame: int) -> Path:
    return dataset / "images" / f"frame-{frame:06d}.color.jpg"


def depth_path(dataset: Path, frame: int) -> Path:
    return dataset / "depth" / f"frame-{frame:06d}.depth.png"


def read_depth(dataset: Path, frame: int, enabled: bool) -> bytes | None:
    path = depth_path(dataset, frame)
    return path.read_bytes() if enabled and path.exists() else None


def nearest_reference(
    truth: Rigid3d, references: dict[str, Rigid3d], max_dist: float, max_angle: float
) -> bool:
    """Whether some reference lies within ``max_dist`` metres and ``max_angle`` degrees."""
    return any(
        d <= max_dist and a <= max_angle
        for d, a in (pose_error(ref, truth) for ref in references.values())
    )


@dataclass
class QueryRecord:
    name: str
    localized: bool
    reason: str | None
    position_error_m: float
    rotation_error_deg: float
    num_inliers: int
    raw_inliers: int
    num_matches: int
    confidence: float
    timings_ms: dict[str, float]
    retrieved: list[str]
    per_reference_inliers: list[int]
    stats: dict[str, float] = field(default_factory=dict)
    ref_within_03m_15deg: bool = False
    ref_within_05m_30deg: bool = False
    retrieval_hit_at_10: bool = False


def record_of(
    name: str,
    result: LocalizationResult,
    truth: Rigid3d | None,
    reference_poses: dict[str, Rigid3d],
) -> QueryRecord:
    pos_err, rot_err = float("inf"), float("inf")
    if truth is not None and result.cam_from_world is not None:
        pos_err, rot_err = pose_error(result.cam_from_world, truth)
    rec = QueryRecord(
        name=name,
        localized=result.localized,
        reason=result.reason,
        position_error_m=pos_err,
        rotation_error_deg=rot_err,
        num_inliers=result.num_inliers,
        raw_inliers=sum(r.num_inliers for r in result.retrieved),
        num_matches=sum(r.num_matches for r in result.retrieved),
        confidence=result.confidence,
        timings_ms=dict(result.timings_ms),
        retrieved=[r.name for r in result.retrieved],
        per_reference_inliers=[r.num_inliers for r in result.retrieved],
        stats=dict(result.stats),
    )
    if truth is not None:
        rec.ref_within_03m_15deg = nearest_reference(truth, reference_poses, 0.3, 15.0)
        rec.ref_within_05m_30deg = nearest_reference(truth, reference_poses, 0.5, 30.0)
        rec.retrieval_hit_at_10 = any(
            np.linalg.norm(reference_poses[r.image_id].center - truth.center) <= 0.5
            and rotation_error_deg(reference_poses[r.image_id].rotation, truth.rotation) <= 30.0
            for r in result.retrieved[:10]
        )
    return rec


def fmt_err(value: float, scale: float, unit: str) -> str:
    return f"{value * scale:8.2f}{unit}" if np.isfinite(value) else f"{'-':>8}{unit}"


def print_record(rec: QueryRecord) -> None:
    t = rec.timings_ms
    times = " ".join(f"{s[:3]}={t.get(s, 0.0):.0f}" for s in STAGES)
    print(
        f"{rec.name:28s} loc={int(rec.localized)} reason={rec.reason or '-':16s} "
        f"pos={fmt_err(rec.position_error_m, 100.0, 'cm')} "
        f"rot={fmt_err(rec.rotation_error_deg, 1.0, '°')} "
        f"inl={rec.num_inliers:5d} (raw {rec.raw_inliers:5d}/{rec.num_matches:5d}) "
        f"ver={rec.stats.get('verified_points', -1):4.0f} conf={rec.confidence:.2f} ms[{times}]",
        flush=True,
    )


def summarize(records: list[QueryRecord], unrelated: list[QueryRecord]) -> dict[str, Any]:
    n = len(records)
    pos = np.array([r.position_error_m for r in records])
    rot = np.array([r.rotation_error_deg for r in records])
    summary: dict[str, Any] = {
        "queries": n,
        "localized": int(sum(r.localized for r in records)),
        "median_position_error_m": float(np.median(pos)) if n else float("nan"),
        "median_rotation_error_deg": float(np.median(rot)) if n else float("nan"),
    }
    for d, a in RECALL_THRESHOLDS:
        hit = (pos <= d) & (rot <= a)
        summary[f"recall_{round(d * 100)}cm_{a:g}deg"] = float(hit.mean()) if n else 0.0
    easy = [r for r in records if r.ref_within_03m_15deg]
    easy_hit = [r for r in easy if r.position_error_m <= 0.10 and r.rotation_error_deg <= 5.0]
    summary["localizable_queries"] = len(easy)
    summary["localizable_recall_10cm_5deg"] = len(easy_hit) / len(easy) if easy else 0.0
    covered = [r for r in records if r.ref_within_05m_30deg]
    summary["retrieval_queries"] = len(covered)
    summary["retrieval_recall_at_10"] = (
        sum(r.retrieval_hit_at_10 for r in covered) / len(covered) if covered else 0.0
    )
    for stage in STAGES:
        values = [r.timings_ms.get(stage, 0.0) for r in records + unrelated]
        summary[f"median_{stage}_ms"] = float(np.median(values)) if values else 0.0
    if unrelated:
        summary["unrelated_queries"] = len(unrelated)
        summary["unrelated_accepted"] = int(sum(r.localized for r in unrelated))
        summary["unrelated_max_raw_inliers"] = int(max(r.raw_inliers for r in unrelated))
    return summary


def print_summary(s: dict[str, Any]) -> None:
    print("\n=== summary ===")
    print(f"queries {s['queries']}, localized {s['localized']}")
    for d, a in RECALL_THRESHOLDS:
        key = f"recall_{round(d * 100)}cm_{a:g}deg"
        print(f"recall ({d * 100:.0f} cm, {a:g}°): {s[key] * 100:5.1f} %")
    print(
        f"median errors: {s['median_position_error_m'] * 100:.2f} cm, "
        f"{s['median_rotation_error_deg']:.2f}°"
    )
    print(
        f"localizable (a reference within 0.3 m & 15°): {s['localizable_queries']} queries, "
        f"{s['localizable_recall_10cm_5deg'] * 100:.1f} % within 10 cm & 5° (target >= 80 %)"
    )
    print(
        f"retrieval recall@10 (a reference within 0.5 m & 30°): "
        f"{s['retrieval_recall_at_10'] * 100:.1f} % of {s['retrieval_queries']} queries"
    )
    print("median timings ms: " + ", ".join(f"{k}={s[f'median_{k}_ms']:.0f}" for k in STAGES))
    if "unrelated_queries" in s:
        print(
            f"unrelated images: {s['unrelated_accepted']} of {s['unrelated_queries']} accepted "
            f"(max raw inliers {s['unrelated_max_raw_inliers']})"
        )


def _finite(value: Any) -> Any:
    """JSON-safe copy: non-finite floats (failed queries' errors) become null."""
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    defaults = EstimatorOptions()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    p.add_argument("--intrinsics", choices=sorted(INTRINSICS), default="colour")
    p.add_argument("--estimator", choices=estimator_names(), default=DEFAULT_ESTIMATOR)
    p.add_argument("--top-k", type=int, default=10)
    p.add_argument("--max-keypoints", type=int, default=SiftOptions().max_keypoints)
    p.add_argument("--contrast-threshold", type=float, default=SiftOptions().contrast_threshold)
    p.add_argument("--ratio", type=float, default=NearestNeighborMatcher().ratio)
    p.add_argument("--min-inliers", type=int, default=defaults.min_inliers)
    p.add_argument("--max-error-px", type=float, default=defaults.max_error_px)
    p.add_argument(
        "--min-verified-points",
        type=int,
        default=defaults.min_verified_points,
        help="3D-verified points needed to accept a pose (0 disables the check)",
    )
    p.add_argument("--limit", type=int, default=None, help="evaluate only the first N queries")
    p.add_argument("--depth", action="store_true", help="pass depth maps where present")
    p.add_argument(
        "--unrelated",
        type=int,
        default=0,
        metavar="N",
        help="also localize N unrelated synthetic images (must all be rejected)",
    )
    p.add_argument("--json", type=Path, default=None, metavar="OUT")
    p.add_argument("--quiet", action="store_true", help="no per-query lines")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    dataset: Path = args.dataset.resolve()
    camera = Camera("PINHOLE", WIDTH, HEIGHT, INTRINSICS[args.intrinsics])
    localizer = Localizer(
        SiftExtractor(
            SiftOptions(
                max_keypoints=args.max_keypoints, contrast_threshold=args.contrast_threshold
            )
        ),
        NearestNeighborMatcher(args.ratio),
        ThumbnailDescriptor(),
        max_pixels=4096 * 4096,
    )
    params = LocalizeParams(
        camera=camera,
        estimator=args.estimator,
        top_k=args.top_k,
        options=EstimatorOptions(
            max_error_px=args.max_error_px,
            min_inliers=args.min_inliers,
            min_verified_points=args.min_verified_points,
        ),
    )
    if args.top_k < 10:
        print(f"note: top-k {args.top_k} < 10, retrieval recall@10 is recall@{args.top_k}")
    poses = load_poses(dataset)
    reference_frames = list(range(0, 500, 5))
    query_frames = list(range(500, 1000, 10))[: args.limit]

    store = InMemoryStore()
    t0 = time.perf_counter()
    for frame in reference_frames:
        data = localizer.describe_reference(
            image_path(dataset, frame).read_bytes(), camera, read_depth(dataset, frame, args.depth)
        )
        name = image_path(dataset, frame).name
        store.add(name, name, camera, poses[frame], data)
    print(f"described {len(store)} references in {time.perf_counter() - t0:.1f} s", flush=True)
    reference_poses = store.poses()

    records = []
    for frame in query_frames:
        path = image_path(dataset, frame)
        result = localizer.localize(
            path.read_bytes(), params, store, read_depth(dataset, frame, args.depth)
        )
        rec = record_of(path.name, result, poses[frame], reference_poses)
        records.append(rec)
        if not args.quiet:
            print_record(rec)

    unrelated = []
    for seed in range(args.unrelated):
        result = localizer.localize(encode_png(unrelated_image(seed)), params, store)
        rec = record_of(f"unrelated-{seed}", result, None, reference_poses)
        unrelated.append(rec)
        if not args.quiet:
            print_record(rec)

    summary = summarize(records, unrelated)
    print_summary(summary)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
            "summary": summary,
            "queries": [asdict(r) for r in records],
            "unrelated": [asdict(r) for r in unrelated],
        }
        args.json.write_text(json.dumps(_finite(payload), indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
