"""How well a map's self-evaluation predicts its real queries: for each dataset and feature
configuration, a server running that configuration builds the map of the dataset's split and
localizes its queries (``slloc eval --url``), then evaluates the map on its own references
(``slloc self-evaluate``); the two sets of figures are printed side by side.

    python -m tools.benchmarks.self_evaluation DATASET[::REFERENCES::QUERIES] [...] \
        [--features xfeat-lg,sift,aliked] [--sample-size 30] [--holdout-radius 0] \
        [--out out/self-evaluation]

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


def _run(command: list[str]) -> None:
    print("$", " ".join(command), file=sys.stderr, flush=True)
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)


def measure(
    dataset: str, features: str, sample_size: int, radius_m: float, out: Path
) -> dict[str, Any]:
    """The query split's and the self-evaluation's figures of one configuration."""
    out.mkdir(parents=True, exist_ok=True)
    path, *rules = dataset.split("::")
    split = ["--references", rules[0], "--queries", rules[1]] if rules else []
    with LocalServer({"SLLOC_FEATURES": features}) as server:
        start = time.perf_counter()
        _run(
            [sys.executable, "-m", "tools.cli", "eval", path, *split, "--url", server.url,
             "--map-preset", features, "--keep-map", "--out", str(out / "queries")]
        )  # fmt: skip
        queries_s = time.perf_counter() - start
        [item] = httpx.get(f"{server.url}/v1/maps").json()["items"]
        start = time.perf_counter()
        _run(
            [sys.executable, "-m", "tools.cli", "self-evaluate", "--url", server.url,
             "--map", item["id"], "--configurations", features,
             "--sample-size", str(sample_size), "--holdout-radius", str(radius_m),
             "--json", str(out / "self.json")]
        )  # fmt: skip
        self_s = time.perf_counter() - start
    [query_summary] = json.loads((out / "queries" / "results.json").read_text())[
        "summaries"
    ].values()
    self_summary = json.loads((out / "self.json").read_text())["result"]["configurations"][features]
    return {
        "queries": query_summary,
        "self": self_summary,
        "queries_s": queries_s,
        "self_s": self_s,
        "references": item["image_count"],
    }


def _row(dataset: str, features: str, figures: dict[str, Any]) -> str:
    keys = [recall_key(m, d) for m, d in THRESHOLDS]
    query, own = figures["queries"], figures["self"]

    def cm(value: float | None) -> str:
        return "–" if value is None else f"{value * 100:.1f}"

    recalls = " | ".join(
        f"{query['recall'][k] * 100:.0f} / {own['recall'][k] * 100:.0f}" for k in keys
    )
    return (
        f"| {dataset} | {features} | {recalls} "
        f"| {cm(query['position_error_m']['median'])} / {cm(own['position_error_m']['median'])} "
        f"| {query['timings_ms']['total']['median']:.0f} / {own['latency_ms']['median']:.0f} "
        f"| {own['held_out']} of {figures['references']} | {own['duration_s']:.0f} |"
    )


def _label(dataset: str) -> str:
    """The dataset's folder name, with its split rules when it has them (two splits of one
    dataset keep apart in the table, the JSON and the output folders)."""
    path, *rules = dataset.split("::")
    folder = Path(path).resolve()
    name = (folder.parent if folder.is_file() else folder).name
    return name if not rules else f"{name} {'/'.join(rules).replace(':', '')}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("datasets", nargs="+")
    parser.add_argument("--features", default="xfeat-lg,sift,aliked")
    parser.add_argument("--sample-size", type=int, default=30)
    parser.add_argument(
        "--holdout-radius", type=float, default=0.0, help="hold out the neighbours this close"
    )
    parser.add_argument("--out", type=Path, default=Path("out/self-evaluation"))
    args = parser.parse_args(argv)
    header = (
        "| dataset | configuration | "
        + " | ".join(f"({m * 100:g} cm, {d:g}°) %" for m, d in THRESHOLDS)
        + " | median cm | p50 ms | held out | took s |"
    )
    rows = [header, "|" + "---|" * (len(THRESHOLDS) + 6)]
    results: dict[str, dict[str, Any]] = {}
    for dataset in args.datasets:
        label = _label(dataset)
        for features in args.features.split(","):
            figures = measure(
                dataset,
                features,
                args.sample_size,
                args.holdout_radius,
                args.out / label.replace(" ", "_").replace("/", "_") / features,
            )
            results[f"{label}/{features}"] = figures
            rows.append(_row(label, features, figures))
            print(rows[-1], file=sys.stderr, flush=True)
    (args.out / "summary.json").write_text(json.dumps(results, indent=1))
    print("queries / self-evaluation in each cell")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
