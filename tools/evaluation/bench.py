"""``slloc bench``: ``/localize`` latency percentiles and throughput with N concurrent clients
on loopback, the server's peak memory, and the service overhead (latency minus the time
inside feature extraction, matching and the estimator) as a share of the latency; with
``--features``, several feature configurations side by side in one run (a server each, all
running, their requests sent in interleaved rounds) with each one's p50 as a ratio of
``sift``'s."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.estimators.registry import DEPTH_ESTIMATORS
from services.features.configs import AUTO, FEATURE_CONFIGS, SIFT, feature_config_names
from tools.evaluation.datasets import PosedImage, open_dataset
from tools.evaluation.evaluate import localize_params
from tools.evaluation.runner import HttpRunner, QueryOutcome, ServiceBusyError
from tools.evaluation.server import LocalServer, is_loopback, memory_mb
from tools.evaluation.split import split_dataset
from tools.synthetic.scene import SyntheticScene, encode_depth_png, encode_png

# stages spent in model inference and solvers (``timings_ms`` of the answer)
COMPUTE_STAGES = ("extract", "match", "estimate")


@dataclass(frozen=True)
class LevelResult:
    """One concurrency level. ``requests`` answered (200) and ``refused`` (503, the server's
    admission control: the client waits its ``Retry-After`` and goes on); latencies are
    client wall times in ms of the answered ones; ``overhead_ratio`` is
    1 − Σ(extract + match + estimate) / Σ latency (queueing behind busy workers counts as
    overhead); ``server_overhead_ratio`` the same against the server's own ``total``."""

    clients: int
    requests: int
    localized: int
    refused: int
    seconds: float
    throughput_rps: float
    latency_p50_ms: float
    latency_p90_ms: float
    latency_p95_ms: float
    latency_p99_ms: float
    overhead_ratio: float
    server_overhead_ratio: float
    median_timings_ms: dict[str, float]


def _synthetic(folder: Path, references: int) -> tuple[list[PosedImage], list[PosedImage]]:
    """A rendered scene's references and 4 queries as PNG files (with depth PNGs) in
    ``folder``."""
    scene = SyntheticScene(seed=0)
    out = []
    for views in (
        scene.views(references, stream=1, prefix="ref"),
        scene.views(4, stream=2, prefix="query"),
    ):
        images = []
        for view in views:
            path, depth = folder / view.name, folder / f"depth-{view.name}"
            path.write_bytes(encode_png(view.image))
            depth.write_bytes(encode_depth_png(view.depth))
            images.append(PosedImage(view.name, path, view.camera, view.cam_from_world, depth))
        out.append(images)
    return out[0], out[1]


@dataclass
class Sent:
    """What one burst of requests got: the answered outcomes, the 503 refusals, its wall
    time."""

    outcomes: list[QueryOutcome]
    refused: int
    seconds: float


def send_requests(
    url: str,
    api_key: str | None,
    map_id: str,
    queries: list[tuple[bytes, bytes | None, dict[str, Any]]],
    clients: int,
    max_requests: int,
    max_seconds: float,
    first_query: int = 0,
) -> Sent:
    """``clients`` threads, each with its own HTTP client, send queries (image, depth,
    params) round-robin from ``queries[first_query]`` on until ``max_requests`` were sent or
    ``max_seconds`` passed."""
    outcomes: list[QueryOutcome] = []
    lock = threading.Lock()
    issued = refused = 0
    deadline = time.monotonic() + max_seconds

    def client() -> None:
        nonlocal issued, refused
        runner = HttpRunner(url, api_key, map_id=map_id)
        try:
            while True:
                with lock:
                    if issued >= max_requests or time.monotonic() >= deadline:
                        return
                    image, depth, params = queries[(first_query + issued) % len(queries)]
                    issued += 1
                try:
                    outcome = runner.localize(image, depth, params)
                except ServiceBusyError as busy:
                    with lock:
                        refused += 1
                    time.sleep(min(busy.retry_after_s, max(0.0, deadline - time.monotonic())))
                    continue
                with lock:
                    outcomes.append(outcome)
        finally:
            runner.close()

    start = time.perf_counter()
    threads = [threading.Thread(target=client) for _ in range(clients)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return Sent(outcomes, refused, time.perf_counter() - start)


def summarize(clients: int, bursts: list[Sent]) -> LevelResult:
    """One level's figures over its bursts (rounds): percentiles of all answered latencies,
    throughput as all answers over the bursts' summed wall time."""
    outcomes = [o for burst in bursts for o in burst.outcomes]
    seconds = sum(burst.seconds for burst in bursts)
    latency = np.array([o.timings_ms["client"] for o in outcomes])
    compute = np.array([sum(o.timings_ms[s] for s in COMPUTE_STAGES) for o in outcomes])
    total = np.array([o.timings_ms["total"] for o in outcomes])
    p50, p90, p95, p99 = np.percentile(latency, [50, 90, 95, 99]) if len(latency) else (np.nan,) * 4
    return LevelResult(
        clients=clients,
        requests=len(outcomes),
        localized=sum(o.localized for o in outcomes),
        refused=sum(burst.refused for burst in bursts),
        seconds=seconds,
        throughput_rps=len(outcomes) / seconds,
        latency_p50_ms=float(p50),
        latency_p90_ms=float(p90),
        latency_p95_ms=float(p95),
        latency_p99_ms=float(p99),
        overhead_ratio=float(1.0 - compute.sum() / latency.sum()) if len(latency) else np.nan,
        server_overhead_ratio=float(1.0 - compute.sum() / total.sum()) if len(total) else np.nan,
        median_timings_ms={
            stage: float(np.median([o.timings_ms[stage] for o in outcomes]))
            for stage in (outcomes[0].timings_ms if outcomes else {})
        },
    )


def round_sizes(total: int, rounds: int) -> list[int]:
    """``total`` requests cut into ``rounds`` near-equal bursts (the first ones larger), no
    empty burst."""
    rounds = max(1, min(rounds, total))
    return [total // rounds + (i < total % rounds) for i in range(rounds)]


@dataclass(frozen=True)
class ConfigurationResult:
    """One feature configuration's levels and its server's peak memory (MiB, None unknown):
    once the references were added, and at the end."""

    features: str
    peak_rss_mb: float | None
    levels: list[LevelResult]
    loading_peak_rss_mb: float | None = None


def markdown(levels: list[LevelResult], peak_mb: float | None) -> str:
    lines = [
        "| clients | requests | refused (503) | throughput (req/s) | p50 ms | p90 ms | p95 ms "
        "| p99 ms | overhead / latency | overhead / server total |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in levels:
        lines.append(
            f"| {r.clients} | {r.requests} | {r.refused} | {r.throughput_rps:.2f} "
            f"| {r.latency_p50_ms:.0f} | {r.latency_p90_ms:.0f} | {r.latency_p95_ms:.0f} "
            f"| {r.latency_p99_ms:.0f} | {r.overhead_ratio * 100:.1f} % "
            f"| {r.server_overhead_ratio * 100:.1f} % |"
        )
    memory = f"{peak_mb:.0f} MiB" if peak_mb is not None else "unknown (give --server-pid)"
    lines += ["", f"Server peak memory (VmHWM): {memory}"]
    return "\n".join(lines) + "\n"


def side_by_side(results: list[ConfigurationResult]) -> str:
    """The configurations' levels in one table, each p50 as a ratio of ``sift``'s p50 at the
    same client count (— without a ``sift`` run)."""
    sift = {r.features: r for r in results}.get(SIFT)
    sift_p50 = {level.clients: level.latency_p50_ms for level in sift.levels} if sift else {}
    lines = [
        "| features | clients | p50 ms | p90 ms | throughput (req/s) | refused (503) "
        "| server peak MiB | p50 / sift p50 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for result in results:
        peak = f"{result.peak_rss_mb:.0f}" if result.peak_rss_mb is not None else "unknown"
        for r in result.levels:
            base = sift_p50.get(r.clients)
            ratio = f"{r.latency_p50_ms / base:.2f}" if base else "—"
            lines.append(
                f"| {result.features} | {r.clients} | {r.latency_p50_ms:.0f} "
                f"| {r.latency_p90_ms:.0f} | {r.throughput_rps:.2f} | {r.refused} | {peak} "
                f"| {ratio} |"
            )
    return "\n".join(lines) + "\n"


@contextmanager
def _server(args: argparse.Namespace, features: str | None) -> Iterator[tuple[str, int | None]]:
    if args.url:
        yield args.url, args.server_pid
        return
    env = {"SLLOC_FEATURES": features} if features else None
    with LocalServer(env) as server:
        yield server.url, server.pid


def _parse(args: argparse.Namespace) -> tuple[list[int], list[str | None]] | str:
    """The client counts and feature configurations (None: the server's), or an error."""
    if args.url and not is_loopback(args.url):
        return "--url must be a loopback address"
    try:
        levels = [int(v) for v in args.clients.split(",")]
    except ValueError:
        return f"bad --clients {args.clients!r}"
    if not args.features:
        return levels, [None]
    if args.url:
        return "--features starts a server per configuration; leave out --url"
    features = [f.strip() for f in args.features.split(",") if f.strip()]
    unknown = [f for f in features if f not in FEATURE_CONFIGS and f != AUTO]
    if unknown or len(set(features)) != len(features):
        return (
            f"--features {args.features!r}: give distinct names of "
            f"{', '.join([AUTO, *feature_config_names()])}"
        )
    return levels, list(features)


@dataclass
class _Target:
    """A running server with the benchmark's map loaded."""

    label: str
    url: str
    pid: int | None
    loader: HttpRunner
    loading_peak_mb: float | None


def _start(
    stack: ExitStack,
    args: argparse.Namespace,
    features: str | None,
    references: list[PosedImage],
) -> _Target:
    """A server for ``features`` (or ``--url``), loaded with ``references`` and their retrieval
    vocabulary trained on all of them (as ``slloc eval`` does and an admin after a bulk load;
    left to the background trainer, the vocabulary of the first references made retrieval
    fail queries that eval localizes)."""
    url, pid = stack.enter_context(_server(args, features))
    # the map is served with the configuration benchmarked, not one its evaluation picks
    loader = HttpRunner(
        url, args.api_key, "slloc-bench", features={"preset": features} if features else None
    )
    stack.callback(loader.close)
    start = time.perf_counter()
    for image in references:
        depth = image.depth_path.read_bytes() if image.depth_path else None
        loader.add_reference(image, depth)
    loader.index_references(len(references))  # the retrieval slloc eval measures accuracy with
    # a map created with the defaults is labelled with the configuration it settled on
    label = features or loader.features
    print(
        f"{label}: loaded {len(references)} references into map {loader.map_id} on {url} "
        f"in {time.perf_counter() - start:.0f} s",
        file=sys.stderr,
        flush=True,
    )
    loading_peak = memory_mb(pid) if pid is not None else None
    return _Target(label, url, pid, loader, loading_peak)


def _bench_interleaved(
    args: argparse.Namespace,
    configurations: list[str | None],
    references: list[PosedImage],
    queries: list[tuple[bytes, bytes | None, dict[str, Any]]],
    levels_wanted: list[int],
    sizes: list[int],
) -> list[ConfigurationResult]:
    """Every configuration's server runs for the whole benchmark; each level's requests go out
    in bursts of ``sizes`` requests (the rounds) that visit the configurations in turn, each
    round starting one configuration later, so a machine whose speed drifts weighs on all of
    them alike. Each burst follows one uncounted request, so that a server which sat idle while
    the others ran is measured warm."""
    with ExitStack() as stack:
        targets = [_start(stack, args, features, references) for features in configurations]
        levels: list[list[LevelResult]] = [[] for _ in targets]
        for clients in levels_wanted:
            bursts: list[list[Sent]] = [[] for _ in targets]
            for r, size in enumerate(sizes):
                for j in range(len(targets)):
                    i = (r + j) % len(targets)
                    target = targets[i]
                    target.loader.localize(*queries[0])  # warm-up after the others ran
                    burst = send_requests(
                        target.url,
                        args.api_key,
                        target.loader.map_id,
                        queries,
                        clients,
                        size,
                        args.duration / len(sizes),
                        first_query=sum(sizes[:r]),
                    )
                    bursts[i].append(burst)
                    print(
                        f"{target.label}, {clients} client(s), round {r + 1}/{len(sizes)}: "
                        f"{len(burst.outcomes)} answered, {burst.refused} refused",
                        file=sys.stderr,
                        flush=True,
                    )
            for i, target in enumerate(targets):
                level = summarize(clients, bursts[i])
                print(
                    f"{target.label}, {clients} client(s): p50 {level.latency_p50_ms:.0f} ms",
                    file=sys.stderr,
                    flush=True,
                )
                levels[i].append(level)
        return [
            ConfigurationResult(
                target.label,
                memory_mb(target.pid) if target.pid is not None else None,
                levels[i],
                target.loading_peak_mb,
            )
            for i, target in enumerate(targets)
        ]


def bench_main(args: argparse.Namespace) -> int:
    logging.getLogger().setLevel(logging.WARNING)  # no INFO line per request
    parsed = _parse(args)
    if isinstance(parsed, str):
        print(f"slloc bench: {parsed}", file=sys.stderr)
        return 2
    levels_wanted, configurations = parsed
    sizes = round_sizes(args.requests, args.rounds if len(configurations) > 1 else 1)
    with tempfile.TemporaryDirectory(prefix="slloc-bench-") as tmp:
        if args.dataset is not None:
            try:
                split = split_dataset(
                    open_dataset(args.dataset, args.images, args.poses),
                    args.references,
                    args.queries,
                )
            except (OSError, ValueError) as exc:
                print(f"slloc bench: {exc}", file=sys.stderr)
                return 2
            references, query_images = split.references, split.queries
        else:
            references, query_images = _synthetic(Path(tmp), args.synthetic_references)
        with_depth = args.estimator in DEPTH_ESTIMATORS
        queries = [
            (
                q.image_path.read_bytes(),
                q.depth_path.read_bytes() if with_depth and q.depth_path else None,
                localize_params(q.camera, args.estimator, args.top_k),
            )
            for q in query_images
        ]
        results = _bench_interleaved(
            args, configurations, references, queries, levels_wanted, sizes
        )
    for result in results:
        print(f"## {result.features}\n\n{markdown(result.levels, result.peak_rss_mb)}")
        if result.loading_peak_rss_mb is not None:
            loading = result.loading_peak_rss_mb
            print(f"Server peak once the references were added: {loading:.0f} MiB\n")
    if len(results) > 1:
        print(side_by_side(results))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps(
            {
                "url": args.url or "local server",
                "estimator": args.estimator,
                "references": len(references),
                "rounds": len(sizes),
                "configurations": [asdict(result) for result in results],
            },
            indent=1,
        )
    )
    print(f"wrote {args.out}", file=sys.stderr)
    return 0
