"""An AR app's localize call, runnable against the README demo map.

What a phone does, simulated on the demo's query: ARKit/ARCore give the camera's intrinsics for
the landscape sensor image (here 3× the upload) and the camera pose in the AR session
(``session_from_cam``, OpenGL axes, a gravity-aligned y-up session frame). The app uploads a
downscaled portrait JPEG with the sensor intrinsics and gravity in the sensor camera frame, asks
for ``world_from_cam`` in OpenGL axes for the sensor camera, and places the map in its session:
``session_from_map = session_from_cam · inverse(map_from_cam)``.

It talks to the service through the Python SDK (``clients/python``, ``slloc_client``).

Run (server up, demo map loaded as in the README example session)::

    .venv/bin/python -m tools.examples.ar_client --map <MAP_ID> --demo demo
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from slloc_client import Client

from services.geometry.pose_conventions import world_from_cam
from services.geometry.rigid import Rigid3d

SENSOR_SCALE = 3  # ARKit: 1920×1440 intrinsics for a 640×480 upload


def demo_query(demo: Path) -> tuple[np.ndarray, dict[str, Any], Rigid3d]:
    """The demo's first query: BGR image, its camera and its true ``cam_from_world``."""
    image = cv2.imread(str(demo / "queries" / "query0000.png"))
    if image is None:
        raise SystemExit(f"no demo query in {demo}: run `slloc synth --out {demo}` first")
    params = json.loads((demo / "queries" / "query0000.params.json").read_text())
    with (demo / "queries" / "ground_truth.csv").open() as f:
        row = next(r for r in csv.DictReader(f) if r["image"] == "query0000.png")
    q = np.array([float(row[k]) for k in ("qw", "qx", "qy", "qz")])
    t = np.array([float(row[k]) for k in ("tx", "ty", "tz")])
    return image, params["camera"], Rigid3d.from_quaternion(q, t)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--api", default="http://127.0.0.1:8000")
    parser.add_argument("--map", required=True, help="map id")
    parser.add_argument("--demo", type=Path, default=Path("demo"), help="`slloc synth` output")
    parser.add_argument("--api-key", default=None)
    args = parser.parse_args()

    image, camera, truth = demo_query(args.demo)
    # the phone's side: a session frame the server does not know (y up, gravity-aligned; the
    # demo map is y-down), and the sensor camera's pose in it, as ARKit's camera.transform
    session_from_map = np.diag([1.0, -1.0, -1.0, 1.0])
    session_from_map[:3, 3] = [0.3, 1.4, -2.0]
    session_from_cam = session_from_map @ world_from_cam(truth, "opengl")

    # 1. intrinsics as the phone gives them: the landscape sensor image, 3× the upload
    sensor = {
        "model": camera["model"],
        "width": camera["width"] * SENSOR_SCALE,
        "height": camera["height"] * SENSOR_SCALE,
        "params": [p * SENSOR_SCALE for p in camera["params"]],
    }
    # 2. gravity in the sensor camera frame (COLMAP axes: x right, y down, z forward), from the
    #    session pose: the session's down (0, -1, 0) in OpenGL camera axes, then y and z flipped
    down_gl = session_from_cam[:3, :3].T @ np.array([0.0, -1.0, 0.0])
    down = down_gl * [1.0, -1.0, -1.0]
    # 3. the upload: the sensor image turned to portrait (90° clockwise) as a JPEG
    portrait = cv2.rotate(image, cv2.ROTATE_90_CLOCKWISE)
    ok, jpeg = cv2.imencode(".jpg", portrait, [cv2.IMWRITE_JPEG_QUALITY, 90])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    params = {
        "camera": sensor,
        "gravity": {"down": down.tolist()},
        "output": {"frames": ["opengl"], "pose_of": "camera"},
    }
    with Client(args.api, api_key=args.api_key, timeout=30.0) as slloc:
        answer = slloc.localize(args.map, jpeg.tobytes(), params=params)
    print("localized:", answer.localized, answer.reason or "")
    adaptation = answer.camera_adaptation
    print(
        "camera_adaptation:",
        adaptation.model_dump_json(exclude={"camera"}) if adaptation else None,
    )
    print("upright_turn_deg:", answer.upright_turn_deg)
    if not answer.localized or answer.world_from_cam is None:
        return
    # 4. place the map in the session: content at x_map is drawn at session_from_map · x_map
    map_from_cam = np.array(answer.world_from_cam["opengl"].matrix)
    estimate = session_from_cam @ np.linalg.inv(map_from_cam)
    error_m = float(np.linalg.norm(estimate[:3, 3] - session_from_map[:3, 3]))
    cos = (np.trace(estimate[:3, :3].T @ session_from_map[:3, :3]) - 1.0) / 2.0
    error_deg = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    print("session_from_map:\n", np.array2string(estimate, precision=4, suppress_small=True))
    print(f"error against the simulated truth: {error_m * 100:.2f} cm, {error_deg:.3f}°")


if __name__ == "__main__":
    main()
