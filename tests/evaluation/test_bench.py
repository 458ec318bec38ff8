"""``slloc bench`` end to end: it starts a real server, loads a small rendered map through the
API, runs 1 and 2 concurrent clients for a few requests and prints the percentiles."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tools import cli
from tools.evaluation.bench import round_sizes


def test_bench_with_one_and_two_clients(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bench.json"
    code = cli.main(
        [
            "bench",
            "--synthetic-references",
            "8",
            "--clients",
            "1,2",
            "--requests",
            "3",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    table = capsys.readouterr().out
    assert "| clients | requests | refused (503) | throughput (req/s) | p50 ms | p90 ms" in table
    assert "Server peak memory (VmHWM):" in table and "MiB" in table
    assert "p50 / sift p50" not in table  # one configuration: no side-by-side table
    result = json.loads(out.read_text())
    assert result["references"] == 8
    (configuration,) = result["configurations"]
    assert [level["clients"] for level in configuration["levels"]] == [1, 2]
    for level in configuration["levels"]:
        assert level["requests"] == 3 and level["refused"] == 0
        assert (
            0
            < level["latency_p50_ms"]
            <= level["latency_p90_ms"]
            <= level["latency_p95_ms"]
            <= level["latency_p99_ms"]
        )
        assert level["throughput_rps"] > 0
        assert 0 < level["overhead_ratio"] < 1 and 0 < level["server_overhead_ratio"] < 1
    assert configuration["peak_rss_mb"] > 50  # the server's, not this process's


def test_bench_configurations_side_by_side_counting_refusals(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two configurations, a server each, their requests in two interleaved rounds; one
    worker and no queue, so that three clients get 503 answers, which are counted and waited
    out."""
    monkeypatch.setenv("SLLOC_LOCALIZE_WORKERS", "1")
    monkeypatch.setenv("SLLOC_MAX_QUEUED", "0")
    out = tmp_path / "bench.json"
    args = ["bench", "--synthetic-references", "6", "--clients", "1,3", "--requests", "6"]
    code = cli.main([*args, "--features", "sift,aliked-nn", "--rounds", "2", "--out", str(out)])
    assert code == 0
    captured = capsys.readouterr()
    table = captured.out
    rounds = [line.split(":")[0] for line in captured.err.splitlines() if ", round " in line]
    assert rounds == [
        f"{features}, {clients} client(s), round {r}/2"
        for clients in (1, 3)
        for r, order in ((1, ("sift", "aliked-nn")), (2, ("aliked-nn", "sift")))
        for features in order
    ]
    assert "## sift" in table and "## aliked-nn" in table
    assert "| features | clients | p50 ms | p90 ms | throughput (req/s) | refused (503)" in table
    result = json.loads(out.read_text())
    assert result["rounds"] == 2
    by_name = {c["features"]: c for c in result["configurations"]}
    assert list(by_name) == ["sift", "aliked-nn"]
    for configuration in by_name.values():
        one, three = configuration["levels"]
        assert one["refused"] == 0 and one["requests"] == 6
        assert three["refused"] > 0 and three["requests"] + three["refused"] == 6
        assert configuration["peak_rss_mb"] > 50
    sift_p50 = by_name["sift"]["levels"][0]["latency_p50_ms"]
    ratio = by_name["aliked-nn"]["levels"][0]["latency_p50_ms"] / sift_p50
    assert f"| sift | 1 | {sift_p50:.0f} |" in table and table.count("| 1.00 |") >= 1
    assert f"| {ratio:.2f} |" in table


@pytest.mark.parametrize(
    ("total", "rounds", "sizes"),
    [(16, 4, [4, 4, 4, 4]), (6, 4, [2, 2, 1, 1]), (3, 4, [1, 1, 1]), (5, 1, [5])],
)
def test_rounds_split_every_request_into_non_empty_bursts(
    total: int, rounds: int, sizes: list[int]
) -> None:
    assert round_sizes(total, rounds) == sizes


def test_bench_refuses_unknown_features(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["bench", "--features", "sift,nope"]) == 2
    assert "nope" in capsys.readouterr().err
    assert cli.main(["bench", "--features", "sift", "--url", "http://127.0.0.1:1"]) == 2
    assert "leave out --url" in capsys.readouterr().err


def test_bench_refuses_remote_url(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["bench", "--url", "http://example.com:8000"]) == 2
    assert "loopback" in capsys.readouterr().err
