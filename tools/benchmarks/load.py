"""The service under load: concurrent localize clients plus a stream of adds and deletes.

Starts ``slloc serve`` (a free loopback port, its own SQLite database unless
``--database-url`` names another, e.g. PostgreSQL), loads the demo scene's references (``slloc
synth``), then for ``--seconds``:
- ``--clients`` threads localize the demo queries back to back;
- one thread adds a reference under a fresh name and deletes it again, over and over;
- one thread times ``GET /v1/health`` every 0.2 s;
and samples the server's resident memory. Prints the answers by status, localize latency,
health latency (median, p99, max), the server's peak and final memory, and checks that the
images stored equal the references loaded + adds acknowledged − deletes acknowledged.

Run from the repository root (after ``slloc synth --out demo``):
``.venv/bin/python -m tools.benchmarks.load [--demo demo] [--clients 8] [--seconds 60]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import threading
import time
from collections import Counter
from pathlib import Path

import httpx
import numpy as np

from tools.evaluation.server import LocalServer, memory_mb


def _percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demo", type=Path, default=Path("demo"))
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--features", default="auto")
    parser.add_argument("--database-url", default=None, help="default: a temporary SQLite file")
    args = parser.parse_args()
    references = sorted((args.demo / "references").glob("*.json"))
    queries = sorted((args.demo / "queries").glob("*.png"))
    if not references or not queries:
        parser.error(f"{args.demo} holds no demo scene (slloc synth --out {args.demo})")
    env = {"SLLOC_FEATURES": args.features}
    if args.database_url:
        env["SLLOC_DATABASE_URL"] = args.database_url
    with LocalServer(env) as server, httpx.Client(base_url=server.url, timeout=120.0) as client:
        name = f"load-{int(time.time())}"
        map_id = client.post("/v1/maps", json={"name": name}).raise_for_status().json()["id"]

        def add(meta: Path, image_name: str | None = None) -> httpx.Response:
            metadata = json.loads(meta.read_text())
            if image_name is not None:
                metadata["name"] = image_name
            return client.post(
                f"/v1/maps/{map_id}/images",
                files={"image": (meta.stem + ".png", meta.with_suffix(".png").read_bytes())},
                data={"metadata": json.dumps(metadata)},
            )

        for meta in references:
            add(meta).raise_for_status()
        print(
            f"map {name}: {len(references)} references; load for {args.seconds:.0f} s", flush=True
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
                    query = queries[i % len(queries)]
                    params = query.with_name(query.stem + ".params.json").read_text()
                    start = time.perf_counter()
                    response = own.post(
                        f"/v1/maps/{map_id}/localize",
                        files={"image": (query.name, query.read_bytes())},
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
    print(
        f"server memory MiB: sampled max {max(memory):.0f}, last {memory[-1]:.0f}, "
        f"peak (VmHWM) {peak if peak is not None else float('nan'):.0f}"
    )
    print(
        f"images stored {stored} = {len(references)} loaded + {acknowledged['adds']} adds "
        f"acknowledged - {acknowledged['deletes']} deletes acknowledged ({expected}): "
        f"{'yes' if stored == expected else 'NO'}"
    )
    return 0 if stored == expected else 1


if __name__ == "__main__":
    raise SystemExit(main())
