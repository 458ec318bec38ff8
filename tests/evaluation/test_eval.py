"""``slloc eval`` through the CLI on a rendered scene: the recall the estimator tests
guarantee, depth reaching depth estimators, partial results after Ctrl-C, and the same poses
in process and against a real ``slloc serve`` subprocess."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from services.estimators.options import RansacOptions
from services.estimators.ransac import searched_in_vain
from services.imaging.decode import decode_image
from tests.evaluation.conftest import NUM_QUERIES, SPLIT_ARGS
from tools import cli
from tools.evaluation.runner import InProcessRunner
from tools.evaluation.server import LocalServer, free_port
from tools.synthetic.scene import SyntheticScene

# auto uses the query's depth when sent and localizes without it (the unrelated image)
ESTIMATORS = "e5p1,e3p1,local_tri_all,auto"


def run_eval(csv_path: Path, out: Path, *extra: str) -> tuple[int, dict[str, Any]]:
    code = cli.main(["eval", str(csv_path), *SPLIT_ARGS, "--out", str(out), *extra])
    return code, json.loads((out / "results.json").read_text())


def compared_args(scene: SyntheticScene) -> list[str]:
    """Estimators, the guaranteed accuracy as the recall threshold, one unrelated image."""
    threshold = f"{0.01 * scene.extent},0.5"
    return ["--estimators", ESTIMATORS, "--threshold", threshold, "--unrelated", "1"]


@pytest.fixture(scope="module")
def in_process(
    synthetic_csv: Path, scene: SyntheticScene, tmp_path_factory: pytest.TempPathFactory
) -> dict[str, Any]:
    # the estimator tests guarantee < 1 % of the scene extent and < 0.5° on these queries
    out = tmp_path_factory.mktemp("eval-in-process")
    code, results = run_eval(synthetic_csv, out, *compared_args(scene))
    assert code == 0
    return results


def test_in_process_reaches_guaranteed_recall(
    in_process: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    summaries = in_process["summaries"]
    assert list(summaries) == [f"sift/{name}" for name in ESTIMATORS.split(",")]
    for config, summary in summaries.items():
        assert summary["queries"] == NUM_QUERIES
        assert list(summary["recall"].values()) == [1.0], config  # e3p1 too: depth was sent
        assert summary["failures"] == {}
        assert summary["unrelated_queries"] == 1 and summary["unrelated_accepted"] == 0
        assert summary["timings_ms"]["total"]["median"] > 0
    assert len(in_process["queries"]) == len(summaries) * (NUM_QUERIES + 1)
    assert not in_process["meta"]["interrupted"]


def test_outputs_written(
    synthetic_csv: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _ = run_eval(synthetic_csv, tmp_path, "--estimators", "e5p1")
    assert code == 0
    table = capsys.readouterr().out
    assert "| sift/e5p1 | 4/4 |" in table and "(10 cm, 10°)" in table
    assert (tmp_path / "report.md").read_text() in table
    for plot in ("errors.png", "timings.png"):
        assert (tmp_path / plot).read_bytes().startswith(b"\x89PNG")


def test_no_intrinsics_sends_no_camera(
    synthetic_csv: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Queries without their camera: the focal length is estimated, the poses are as accurate
    as with it (or the query is refused), and no confident answer is wrong."""
    code, results = run_eval(
        synthetic_csv, tmp_path, "--estimators", "local_tri_all", "--no-intrinsics"
    )
    assert code == 0 and results["meta"]["intrinsics"] is False
    summary = results["summaries"]["sift/local_tri_all"]
    assert summary["confident_wrong"] == 0 and summary["confident"] >= 1
    assert set(summary["failures"]) <= {"focal_unobservable"}
    for query in results["queries"]:
        if query["localized"]:
            assert query["position_error_m"] < 0.05
    assert "Answers with confidence > 0.8" in capsys.readouterr().out


def test_ctrl_c_leaves_partial_results(
    synthetic_csv: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    original = InProcessRunner.localize_each
    calls = 0

    def interrupting(self: InProcessRunner, *args: Any) -> Any:
        nonlocal calls
        calls += 1
        if calls == 3:
            raise KeyboardInterrupt
        return original(self, *args)

    monkeypatch.setattr(InProcessRunner, "localize_each", interrupting)
    code, results = run_eval(synthetic_csv, tmp_path, "--estimators", "e5p1")
    assert code == 130
    assert results["meta"]["interrupted"] is True
    assert [q["query"] for q in results["queries"]] == [
        "images/query0000.png",
        "images/query0001.png",
    ]
    assert results["summaries"]["sift/e5p1"]["queries"] == 2
    assert (tmp_path / "errors.png").is_file()


def test_a_query_that_raises_is_its_failure_and_the_run_goes_on(
    synthetic_csv: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Regression: a singular matrix in one query's pose verification aborted the run."""
    original = InProcessRunner.localize_each
    calls = 0

    def singular_once(self: InProcessRunner, *args: Any) -> Any:
        nonlocal calls
        calls += 1
        if calls == 2:
            raise np.linalg.LinAlgError("Singular matrix")
        return original(self, *args)

    monkeypatch.setattr(InProcessRunner, "localize_each", singular_once)
    code, results = run_eval(synthetic_csv, tmp_path, "--estimators", "e5p1")
    assert code == 0
    assert results["meta"]["error"] is None
    queries = results["queries"]
    assert len(queries) == NUM_QUERIES
    assert [q["localized"] for q in queries] == [True, False, True, True]
    assert queries[1]["reason"] == "error: LinAlgError"
    summary = results["summaries"]["sift/e5p1"]
    assert summary["failures"] == {"error: LinAlgError": 1}


def test_queries_resized_are_sent_with_their_camera_scaled(
    synthetic_csv: Path, scene: SyntheticScene, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--query-scale 1.5``: each query reaches the service 1.5 times the size, with a camera
    of that size (a wrong one would cost the recall) and without depth."""
    original = InProcessRunner.localize_each
    sent: list[tuple[tuple[int, int], int, bool]] = []

    def recording(self: InProcessRunner, image: bytes, depth: Any, params: Any, *rest: Any) -> Any:
        height, width = decode_image(image, 100_000_000).shape[:2]
        sent.append(((width, height), params["camera"]["width"], depth is None))
        return original(self, image, depth, params, *rest)

    monkeypatch.setattr(InProcessRunner, "localize_each", recording)
    threshold = f"{0.01 * scene.extent},0.5"
    code, results = run_eval(
        synthetic_csv,
        tmp_path,
        "--estimators",
        "local_tri_all,e3p1",
        "--threshold",
        threshold,
        "--query-scale",
        "1.5",
    )
    assert code == 0 and results["meta"]["query_scale"] == 1.5
    size = (round(1.5 * scene.camera.width), round(1.5 * scene.camera.height))
    assert sent == [(size, size[0], True)] * NUM_QUERIES
    summaries = results["summaries"]
    assert list(summaries["sift/local_tri_all"]["recall"].values()) == [1.0]
    assert summaries["sift/e3p1"]["failures"]  # e3p1 needs the query's depth


def test_a_query_scale_out_of_range_is_refused(
    synthetic_csv: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = cli.main(["eval", str(synthetic_csv), *SPLIT_ARGS, "--query-scale", "8"])
    assert code == 2
    assert "--query-scale must be within 0.25-4" in capsys.readouterr().err


@pytest.fixture(scope="module")
def server() -> Iterator[LocalServer]:
    with LocalServer() as running:
        yield running


def test_http_mode_gives_the_same_poses(
    in_process: dict[str, Any],
    server: LocalServer,
    synthetic_csv: Path,
    tmp_path: Path,
    scene: SyntheticScene,
) -> None:
    """Same inputs, same seed, same code path behind the HTTP layer: identical poses (the
    JSON round trip of float64 is exact; 1e-9 leaves room for nothing else)."""
    code, results = run_eval(synthetic_csv, tmp_path, "--url", server.url, *compared_args(scene))
    assert code == 0
    assert results["meta"]["mode"] == "http"

    def poses(res: dict[str, Any]) -> dict[tuple[str, str], Any]:
        return {
            (q["config"].split("/")[-1], q["query"]): q["cam_from_world"] for q in res["queries"]
        }

    http, local = poses(results), poses(in_process)
    assert http.keys() == local.keys()

    # the same outcome for every query, the unrelated image included (a depth estimator on
    # it: missing_depth, not a 422); the one engine number the answer carries, whether the
    # query was retrieved again wider, only for the unrelated image (unsure: not localized),
    # unless its pose search drew every hypothesis without a pose
    def outcomes(res: dict[str, Any]) -> dict[tuple[str, str], Any]:
        return {(q["config"].split("/")[-1], q["query"]): q for q in res["queries"]}

    http_outcomes, local_outcomes = outcomes(results), outcomes(in_process)
    for key, local_query in local_outcomes.items():
        query = http_outcomes[key]
        assert query["reason"] == local_query["reason"], key
        widened = query["stats"]["wider_retrieval"]
        vain = searched_in_vain(local_query["stats"], RansacOptions())
        unsure = key[1].startswith("unrelated") and key[0] != "e3p1" and not vain
        assert widened == float(unsure), key
        # in process, where the estimators share one matching, each says its own
        assert local_query["stats"]["wider_retrieval"] == widened, key
    for key, pose in local.items():
        if pose is None:
            assert http[key] is None, key
            continue
        for part in ("rotation", "translation"):
            np.testing.assert_allclose(
                http[key][part], pose[part], rtol=0, atol=1e-9, err_msg=str(key)
            )
    for config, summary in results["summaries"].items():
        assert list(summary["recall"].values()) == [1.0], config
    # the evaluation map was deleted at the end (no --keep-map)
    assert httpx.get(f"{server.url}/v1/maps").json()["total"] == 0


def test_unreachable_server_is_reported(synthetic_csv: Path, tmp_path: Path) -> None:
    code, results = run_eval(synthetic_csv, tmp_path, "--url", f"http://127.0.0.1:{free_port()}")
    assert code == 1
    assert "GET /v1/health" in results["meta"]["error"]
    assert results["queries"] == []
