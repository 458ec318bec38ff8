"""Several frames with their AR-session poses, localized jointly: in process, the map of a
dataset's split built with one feature configuration, each query sent together with the next
query(ies) of the split as the frames of one session (the ground truth's poses placed in a
session turned and moved from the map). Prints recall of the first frame's pose at (5 cm, 5°)
and (25 cm, 2°), its median error, the answers above confidence 0.8 and those of them more
than 25 cm or 5° off, the localized answers more than 1 m off, those with an uncertainty and
those of them within 3 times it, failures by reason and the median time; every answer, with
the joint estimate's stats, in ``OUT/results.json``.

    python -m tools.benchmarks.session_frames DATASET [--references RULE] [--queries RULE] \
        [--features xfeat-lg] [--frames 2] [--out out/session-frames]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from app.schemas.geometry import CameraSchema
from app.schemas.localize import LocalizeParamsIn
from app.schemas.session import MAX_FRAMES_SCHEMA as MAX_FRAMES
from app.settings import get_settings
from app.usecases.localize_frames import SessionFrame, localize_with_session
from services.geometry.rigid import Rigid3d, pose_error
from tools.evaluation.datasets import open_dataset
from tools.evaluation.metrics import CONFIDENT, WRONG_DEG, WRONG_M
from tools.evaluation.runner import InProcessRunner
from tools.evaluation.split import split_dataset

# the session's placement in the map: turned 30° about the vertical and moved
MAP_FROM_SESSION = Rigid3d.from_quaternion(
    np.array([0.9659258, 0.0, 0.2588190, 0.0]), np.array([3.0, -0.5, 2.0])
)
THRESHOLDS = ((0.05, 5.0), (0.25, 2.0))
FAR_M = 1.0


def summarize(answers: list[dict[str, Any]]) -> dict[str, Any]:
    """The figures of the answers (``error_m`` / ``error_deg`` of the first frame's pose,
    ``inf`` when not localized; ``stats`` the joint estimate's, with its uncertainty when it
    has one)."""
    located = [a for a in answers if a["localized"]]
    sized = [a for a in located if "structure_position_sigma_m" in a.get("stats", {})]
    confident = [a for a in located if a["confidence"] > CONFIDENT]
    reasons = Counter(a["reason"] for a in answers if not a["localized"])
    return {
        "queries": len(answers),
        "localized": len(located),
        "recall": {
            f"{m * 100:g}cm_{d:g}deg": sum(
                a["error_m"] <= m and a["error_deg"] <= d for a in located
            )
            / max(len(answers), 1)
            for m, d in THRESHOLDS
        },
        "median_error_m": float(np.median([a["error_m"] for a in answers])) if answers else None,
        "confident": len(confident),
        "confident_wrong": sum(
            a["error_m"] > WRONG_M or a["error_deg"] > WRONG_DEG for a in confident
        ),
        "far": sum(a["error_m"] > FAR_M for a in located),
        "with_uncertainty": len(sized),
        "within_3_uncertainty": sum(
            a["error_m"] <= 3 * a["stats"]["structure_position_sigma_m"]
            and a["error_deg"] <= 3 * a["stats"]["structure_rotation_sigma_deg"]
            for a in sized
        ),
        "failures": dict(reasons),
        "median_ms": float(np.median([a["ms"] for a in answers])) if answers else None,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--references")
    parser.add_argument("--queries")
    parser.add_argument("--features", default="xfeat-lg")
    parser.add_argument("--frames", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("out/session-frames"))
    args = parser.parse_args()
    if not 2 <= args.frames <= MAX_FRAMES:
        parser.error(f"--frames must be within 2-{MAX_FRAMES}")
    split = split_dataset(open_dataset(args.dataset), args.references, args.queries)
    runner = InProcessRunner(args.features, get_settings().models_dir)
    answers: list[dict[str, Any]] = []
    try:
        for image in split.references:
            runner.add_reference(image, None)
        runner.index_references(len(split.references))
        sessions = [
            split.queries[i : i + args.frames] for i in range(len(split.queries) - args.frames + 1)
        ]
        for k, views in enumerate(sessions):
            frames = [
                SessionFrame(v.camera, v.cam_from_world.compose(MAP_FROM_SESSION)) for v in views
            ]
            camera = CameraSchema.from_camera(views[0].camera).model_dump()
            request = LocalizeParamsIn.model_validate({"camera": camera}).to_request()
            start = time.perf_counter()
            answer = localize_with_session(
                runner.context,
                runner.map_id,
                request,
                frames,
                [v.image_path.read_bytes() for v in views],
                max_frames=args.frames,
            ).result
            ms = (time.perf_counter() - start) * 1e3
            pose = answer.cam_from_world
            error = pose_error(pose, views[0].cam_from_world) if pose else (np.inf, np.inf)
            answers.append(
                {
                    "query": views[0].name,
                    "localized": answer.localized,
                    "reason": answer.reason,
                    "confidence": answer.confidence,
                    "error_m": float(error[0]),
                    "error_deg": float(error[1]),
                    "ms": ms,
                    "stats": answer.stats,
                }
            )
            said = f"{error[0] * 100:.1f} cm" if answer.localized else answer.reason
            print(f"[{k + 1}/{len(sessions)}] {views[0].name}: {said}", file=sys.stderr, flush=True)
    finally:
        runner.close()
    summary = summarize(answers)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps({"summary": summary, "answers": answers}))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
