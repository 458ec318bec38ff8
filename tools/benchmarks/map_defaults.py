"""What a map created with the defaults serves: a server with the default settings builds the
map of each dataset's split (``features: auto``), waits until the map is ready (its
self-evaluations have run and it has taken the configuration recommended), then localizes
the queries (``slloc eval --url``). Prints, per dataset, the configuration taken, the
evaluations that ran while the map was built, how long the map took to be ready, and the
queries' figures.

    python -m tools.benchmarks.map_defaults DATASET[::REFERENCES::QUERIES] [...] \
        [--env NAME=VALUE ...] [--out out/map-defaults]

A dataset is what ``slloc eval`` takes, optionally with its split rules (default: the
dataset's suggestion), e.g. ``kitti05/frames.csv::range:0-299 every:3::range:1-299 every:6``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from services.self_evaluation.summary import THRESHOLDS, recall_key
from tools.evaluation.server import LocalServer


def measure(dataset: str, env: dict[str, str], out: Path) -> dict[str, Any]:
    """The map's configuration, its evaluations and the queries' figures of one dataset."""
    out.mkdir(parents=True, exist_ok=True)
    path, *rules = dataset.split("::")
    split = ["--references", rules[0], "--queries", rules[1]] if rules else []
    with LocalServer(env) as server:
        start = time.perf_counter()
        command = [
            sys.executable, "-m", "tools.cli", "eval", path, *split, "--url", server.url,
            "--keep-map", "--out", str(out / "queries"),
        ]  # fmt: skip
        print("$", " ".join(command), file=sys.stderr, flush=True)
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        took_s = time.perf_counter() - start
        [item] = httpx.get(f"{server.url}/v1/maps").json()["items"]
        evaluations = httpx.get(
            f"{server.url}/v1/maps/{item['id']}/evaluations", params={"limit": 100}
        ).json()["items"]
    [summary] = json.loads((out / "queries" / "results.json").read_text())["summaries"].values()
    return {
        "preset": item["features"]["preset"],
        "references": item["image_count"],
        "evaluations": [
            {
                "references": (e["result"] or {}).get("references"),
                "recommended": (e["result"] or {}).get("recommended"),
                "state": e["state"],
                "duration_s": sum(
                    c["duration_s"] for c in (e["result"] or {}).get("configurations", {}).values()
                ),
                "configurations": {
                    name: {
                        key: c[key]
                        for key in ("recall", "position_error_m", "latency_ms", "duration_s")
                    }
                    for name, c in (e["result"] or {}).get("configurations", {}).items()
                },
            }
            for e in reversed(evaluations)
        ],
        "eval_s": took_s,
        "queries": summary,
    }


def _row(dataset: str, figures: dict[str, Any]) -> str:
    query = figures["queries"]
    recalls = " | ".join(f"{query['recall'][recall_key(m, d)] * 100:.0f}" for m, d in THRESHOLDS)
    median = query["position_error_m"]["median"]
    latency = query["timings_ms"].get("total", {}).get("median")  # none when none answered
    runs = ", ".join(
        f"{e['references']}→{e['recommended']} ({e['duration_s']:.0f} s)"
        for e in figures["evaluations"]
    )
    return (
        f"| {dataset} | {figures['preset']} | {recalls} "
        f"| {'–' if median is None else f'{median * 100:.1f}'} "
        f"| {'–' if latency is None else f'{latency:.0f}'} | {runs or 'none'} "
        f"| {figures['eval_s']:.0f} |"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("datasets", nargs="+")
    parser.add_argument(
        "--env", action="append", default=[], metavar="NAME=VALUE", help="a server setting"
    )
    parser.add_argument("--out", type=Path, default=Path("out/map-defaults"))
    args = parser.parse_args(argv)
    env = dict(item.split("=", 1) for item in args.env)
    header = (
        "| dataset | configuration taken | "
        + " | ".join(f"({m * 100:g} cm, {d:g}°) %" for m, d in THRESHOLDS)
        + " | median cm | p50 ms | evaluations: references → recommended (took) | eval s |"
    )
    rows = [header, "|" + "---|" * (len(THRESHOLDS) + 6)]
    results: dict[str, dict[str, Any]] = {}
    for dataset in args.datasets:
        name = Path(dataset.split("::")[0]).resolve()
        name = name.parent if name.is_file() else name
        figures = measure(dataset, env, args.out / name.name)
        results[name.name] = figures
        rows.append(_row(name.name, figures))
        print(rows[-1], file=sys.stderr, flush=True)
    (args.out / "summary.json").write_text(json.dumps(results, indent=1))
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
