"""``slloc bench`` end to end: it starts a real server, loads a small rendered map through the
API, runs 1 and 2 concurrent clients for a few requests and prints the percentiles."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tools import cli


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
    assert "| clients | requests | throughput (req/s) | p50 ms | p95 ms | p99 ms" in table
    assert "Server peak memory (VmHWM):" in table and "MiB" in table
    result = json.loads(out.read_text())
    assert result["references"] == 8
    assert [level["clients"] for level in result["levels"]] == [1, 2]
    for level in result["levels"]:
        assert level["requests"] == 3
        assert 0 < level["latency_p50_ms"] <= level["latency_p95_ms"] <= level["latency_p99_ms"]
        assert level["throughput_rps"] > 0
        assert 0 < level["overhead_ratio"] < 1 and 0 < level["server_overhead_ratio"] < 1
    assert result["peak_rss_mb"] > 50  # the server's, not this process's


def test_bench_refuses_remote_url(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["bench", "--url", "http://example.com:8000"]) == 2
    assert "loopback" in capsys.readouterr().err
