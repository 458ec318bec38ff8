"""The service under load: concurrent localize clients plus a stream of adds and deletes.

Starts ``slloc serve`` (a free loopback port, its own SQLite database unless
``--database-url`` names another, e.g. PostgreSQL), loads the demo scene's references (``slloc
synth``), then for ``--seconds``:
- ``--clients`` threads localize the demo queries back to back;
- one thread adds a reference under a fresh name and deletes it again, over and over;
- one thread times ``GET /v1/health`` every 0.2 s;
and samples the server's resident memory. Prints the answers by status, localize latency,
health latency (median, p99, max), the server's peak memory next to the memory bound its
``/v1/health`` states (``services/runtime/memory.py``), and checks that the images stored
equal the references loaded + adds acknowledged − deletes acknowledged.

``--max-side`` creates the map with that ``features.max_side`` (the largest allowed:
``SLLOC_MAX_SIDE``) and ``--scale`` enlarges every image (and its intrinsics) so that the
extractor sees that many pixels.

Run from the repository root (after ``slloc synth --out demo``):
``.venv/bin/python -m tools.benchmarks.load [--demo demo] [--clients 8] [--seconds 60]
[--max-side 1024 --scale 2]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import threading
import time
from collections import Counter
from pathlib import Path

import cv2
import httpx
import numpy as np

from tools.evaluation.server import LocalServer, memory_mb


def _percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def _scaled(png: Path, camera: dict[str, object], scale: float) -> tuple[bytes, dict[str, object]]:
    """The image enlarged ``scale`` times as PNG bytes, and its camera to match."""
    if scale == 1.0:
        return png.read_bytes(), camera
    image = cv2.imread(str(png))
    if image is None:
        raise OSError(f"cannot read {png}")
    width, height = round(image.shape[1] * scale), round(image.shape[0] * scale)
    ok, data = cv2.imencode(".png", cv2.resize(image, (width, height)))
    assert ok
    params = [float(v) * scale for v in camera["params"]]  # type: ignore[attr-defined]
    return data.tobytes(), {**camera, "width": width, "height": height, "params": params}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demo", type=Path, default=Path("demo"))
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--features", default="auto")
    parser.add_argument("--database-url", default=None, help="default: a temporary SQLite file")
    parser.add_argument("--max-side", type=int, default=None, help="the map's features.max_side")
    parser.add_argument("--scale", type=float, default=1.0, help="enlarge every image this much")
    args = parser.parse_args()
    references = sorted((args.demo / "references").glob("*.json"))
    queries = sorted((args.demo / "queries").glob("*.png"))
    if not references or not queries:
        parser.error(f"{args.demo} holds no demo scene (slloc synth --out {args.demo})")
    env = {"SLLOC_FEATURES": args.features}
    if args.database_url:
        env["SLLOC_DATABASE_URL"] = args.database_url
    reference_data = {}
    for meta in references:
        metadata = json.loads(meta.read_text())
        png, metadata["camera"] = _scaled(meta.with_suffix(".png"), metadata["camera"], args.scale)
        reference_data[meta] = (png, metadata)
    query_data = []
    for query in queries:
        params = json.loads(query.with_name(query.stem + ".params.json").read_text())
        png, params["camera"] = _scaled(query, params["camera"], args.scale)
        query_data.append((query.name, png, json.dumps(params)))
    with LocalServer(env) as server, httpx.Client(base_url=server.url, timeout=120.0) as client:
        name = f"load-{int(time.time())}"
        features = {} if args.max_side is None else {"features": {"max_side": args.max_side}}
        created_map = client.post("/v1/maps", json={"name": name, **features})
        map_id = created_map.raise_for_status().json()["id"]
        runtime = client.get("/v1/health").raise_for_status().json()["runtime"]

        def add(meta: Path, image_name: str | None = None) -> httpx.Response:
            png, metadata = reference_data[meta]
            if image_name is not None:
                metadata = {**metadata, "name": image_name}
            return client.post(
                f"/v1/maps/{map_id}/images",
                files={"image": (meta.stem + ".png", png)},
                data={"metadata": json.dumps(metadata)},
            )

        for meta in references:
            add(meta).raise_for_status()
        size = reference_data[references[0]][1]["camera"]
        print(
            f"map {name} ({created_map.json()['features']}): {len(references)} references of "
            f"{size['width']}×{size['height']}; load for {args.seconds:.0f} s",
            flush=True,
        )

        stop = time.monotonic() + args.seconds
        statuses: Counter[str] = Counter()
        localize_ms: list[float] = []
        health_ms: list[float] = []
        memory: list[float] = []
        acknowledged = {"adds": 0, "deletes": 0}
        lock = threading.Lock()

        def localizer(worker: int) -> None:
            with httpx.Client(base_url=server.url, timeout=120.0) as own:
                i = worker
                while time.monotonic() < stop:
                    query_name, png, params = query_data[i % len(query_data)]
                    start = time.perf_counter()
                    response = own.post(
                        f"/v1/maps/{map_id}/localize",
                        files={"image": (query_name, png)},
                        data={"params": params},
                    )
                    elapsed = (time.perf_counter() - start) * 1000
                    with lock:
                        statuses[f"localize {response.status_code}"] += 1
                        if response.status_code == 200:
                            localize_ms.append(elapsed)
                    if response.status_code == 503:
                        time.sleep(float(response.headers.get("Retry-After", "1")))
                    i += 1

        def churn() -> None:
            with httpx.Client(base_url=server.url, timeout=120.0) as own:
                n = 0
                while time.monotonic() < stop:
                    meta = references[n % len(references)]
                    created = add(meta, f"churn{n:05d}.png")
                    with lock:
                        statuses[f"add {created.status_code}"] += 1
                    if created.status_code == 201:
                        acknowledged["adds"] += 1
                        image_id = created.json()["id"]
                        deleted = own.delete(f"/v1/maps/{map_id}/images/{image_id}")
                        with lock:
                            statuses[f"delete {deleted.status_code}"] += 1
                        if deleted.status_code == 204:
                            acknowledged["deletes"] += 1
                    elif created.status_code == 503:
                        time.sleep(float(created.headers.get("Retry-After", "1")))
                    n += 1

        def health() -> None:
            with httpx.Client(base_url=server.url, timeout=30.0) as own:
                while time.monotonic() < stop:
                    start = time.perf_counter()
                    own.get("/v1/health").raise_for_status()
                    health_ms.append((time.perf_counter() - start) * 1000)
                    rss = memory_mb(server.pid, "VmRSS")
                    if rss is not None:
                        memory.append(rss)
                    time.sleep(0.2)

        threads = [threading.Thread(target=localizer, args=(w,)) for w in range(args.clients)]
        threads += [threading.Thread(target=churn), threading.Thread(target=health)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        stored = client.get(f"/v1/maps/{map_id}").raise_for_status().json()["image_count"]
        # the bound now, the retrieval index included
        runtime = client.get("/v1/health").raise_for_status().json()["runtime"]
        expected = len(references) + acknowledged["adds"] - acknowledged["deletes"]
        peak = memory_mb(server.pid)
        client.delete(f"/v1/maps/{map_id}")

    print("answers:", dict(sorted(statuses.items())))
    print(
        f"localize 200 latency ms: median {statistics.median(localize_ms):.0f}, "
        f"p90 {_percentile(localize_ms, 90):.0f}, max {max(localize_ms):.0f}"
        if localize_ms
        else "no localize answered 200"
    )
    print(
        f"health latency ms over {len(health_ms)} probes: median "
        f"{statistics.median(health_ms):.1f}, p99 {_percentile(health_ms, 99):.1f}, "
        f"max {max(health_ms):.1f}"
    )
    bound = runtime["memory_bound_mib"]
    print(
        f"server memory MiB: sampled max {max(memory):.0f}, last {memory[-1]:.0f}, "
        f"peak (VmHWM) {peak if peak is not None else float('nan'):.0f}; bound {bound:.0f} "
        f"({', '.join(f'{k} {v:.0f}' for k, v in runtime['memory_terms_mib'].items())}): "
        f"{'under' if peak is not None and peak <= bound else 'OVER'}"
    )
    print(
        f"summary: health p50 {statistics.median(health_ms):.1f} ms, p99 "
        f"{_percentile(health_ms, 99):.1f} ms; localizes {len(localize_ms)}, adds "
        f"{acknowledged['adds']}, deletes {acknowledged['deletes']}; peak {peak or 0:.0f} MiB "
        f"of bound {bound:.0f} MiB; stored = adds - deletes: "
        f"{'yes' if stored == expected else 'NO'}"
    )
    print(
        f"images stored {stored} = {len(references)} loaded + {acknowledged['adds']} adds "
        f"acknowledged - {acknowledged['deletes']} deletes acknowledged ({expected}): "
        f"{'yes' if stored == expected else 'NO'}"
    )
    return 0 if stored == expected else 1


if __name__ == "__main__":
    raise SystemExit(main())
