"""Arguments of ``slloc eval``, ``slloc calibrate``, ``slloc bench`` and ``slloc
self-evaluate`` (light imports: the CLI builds them for every command)."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.estimators.registry import DEFAULT_ESTIMATOR, estimator_names
from services.features.configs import AUTO, feature_config_names
from tools.evaluation.metrics import DEFAULT_THRESHOLDS


def _positive_int(value: str) -> int:
    number = int(value)
    if number < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return number


def add_dataset_arguments(parser: argparse.ArgumentParser, required: bool) -> None:
    parser.add_argument(
        "dataset",
        type=Path,
        nargs=None if required else "?",
        help="an import CSV, a redkitchen-layout folder, or a COLMAP model folder (+ --images)",
    )
    parser.add_argument("--images", type=Path, help="image folder of a COLMAP model")
    parser.add_argument(
        "--poses",
        help="a redkitchen folder's ground-truth file (default: poses_c2w_sfm.csv, the colour "
        "camera's, where it exists; poses_c2w.csv is the depth camera's track)",
    )
    parser.add_argument(
        "--references",
        help='reference rule, e.g. "range:0-499 every:5", "list:refs.txt", "rest" '
        "(default: the dataset's suggestion, else everything but the queries)",
    )
    parser.add_argument(
        "--queries",
        help='query rule, e.g. "range:500-999 every:10" (default: the dataset\'s suggestion, '
        "else every:10)",
    )


def add_eval_arguments(parser: argparse.ArgumentParser) -> None:
    add_dataset_arguments(parser, required=True)
    parser.add_argument(
        "--estimators",
        default=DEFAULT_ESTIMATOR,
        help=f"comma-separated estimator names or 'all' ({', '.join(estimator_names())})",
    )
    parser.add_argument(
        "--features",
        default=AUTO,
        help="comma-separated feature configurations or 'all', in process only; auto = the "
        "server's default "
        f"({', '.join(feature_config_names())}); with --url the server's are used",
    )
    parser.add_argument("--url", help="evaluate against this running server instead")
    parser.add_argument("--api-key", help="X-API-Key for --url (an admin key)")
    parser.add_argument("--keep-map", action="store_true", help="with --url: keep the map")
    parser.add_argument("--top-k", type=int, default=10)
    parser.add_argument("--max-error-px", type=float, help="inlier threshold (service default)")
    parser.add_argument(
        "--threshold",
        action="append",
        metavar="M,DEG",
        help="recall threshold in metres and degrees, repeatable (default: "
        + " ".join(f"{m:g},{d:g}" for m, d in DEFAULT_THRESHOLDS)
        + ")",
    )
    parser.add_argument("--no-depth", action="store_true", help="never send depth maps")
    parser.add_argument(
        "--no-intrinsics",
        action="store_true",
        help="send queries without their camera (the service estimates the focal length)",
    )
    parser.add_argument(
        "--unrelated",
        type=int,
        default=0,
        metavar="N",
        help="also localize N unrelated images (false accepts)",
    )
    parser.add_argument(
        "--unrelated-seed",
        type=int,
        default=0,
        metavar="S",
        help="the unrelated images are those of seeds S, S+1, ...",
    )
    parser.add_argument(
        "--unrelated-images",
        type=Path,
        metavar="DIR",
        help="also localize every JPEG/PNG in DIR, images of another scene (false accepts)",
    )
    parser.add_argument("--max-queries", type=int, metavar="N", help="only the first N queries")
    parser.add_argument(
        "--wrong-focal",
        type=int,
        default=0,
        metavar="N",
        help="also localize the first N queries with a wrong focal length (×1.5, ×0.67 in turn)",
    )
    parser.add_argument(
        "--query-scale",
        type=float,
        default=1.0,
        metavar="F",
        help="send every query resized F times (0.25-4), its camera scaled alike and without "
        "depth: queries from a camera of another resolution than the map's",
    )
    parser.add_argument(
        "--max-keypoints", type=int, metavar="N", help="the map's keypoint budget per image"
    )
    parser.add_argument(
        "--max-side", type=int, metavar="PX", help="the map's longer image side for features"
    )
    parser.add_argument(
        "--second-opinion",
        metavar="NAME",
        default="",
        help="in process: a query the map's configuration does not localize is localized "
        "again by configuration NAME against its retrieved references, as the server's "
        "SLLOC_SECOND_OPINION does (default: none; with --url the server's setting applies)",
    )
    parser.add_argument(
        "--map-preset",
        metavar="NAME",
        help="with --url: the created map's feature configuration (default: auto, the "
        "server's until the map's self-evaluation recommends one; the queries wait for it)",
    )
    parser.add_argument("--out", type=Path, default=Path("out/eval"), help="output folder")


def add_bench_arguments(parser: argparse.ArgumentParser) -> None:
    add_dataset_arguments(parser, required=False)
    parser.add_argument(
        "--url", help="benchmark this server on loopback (default: start one on a free port)"
    )
    parser.add_argument("--api-key", help="X-API-Key for --url (an admin key)")
    parser.add_argument(
        "--server-pid", type=int, help="with --url: the server's process id, for its peak memory"
    )
    parser.add_argument(
        "--synthetic-references",
        type=int,
        default=24,
        metavar="N",
        help="without a dataset: render a synthetic scene with N references",
    )
    parser.add_argument(
        "--features",
        help="comma-separated feature configurations to measure side by side, a server each "
        "(e.g. aliked,sift; default: the server's own); with sift among them each p50 is "
        "also printed as a ratio of sift's",
    )
    parser.add_argument("--clients", default="1,2,4", help="concurrent clients per level")
    parser.add_argument("--requests", type=int, default=20, help="requests per level (at most)")
    parser.add_argument("--duration", type=float, default=120.0, help="seconds per level (at most)")
    parser.add_argument(
        "--rounds",
        type=_positive_int,
        default=4,
        help="bursts each level's requests are sent in, visiting the --features servers in "
        "turn so that a drifting machine weighs on them alike (default 4)",
    )
    parser.add_argument("--estimator", default=DEFAULT_ESTIMATOR, choices=estimator_names())
    parser.add_argument("--top-k", type=int, default=10)
    parser.add_argument("--out", type=Path, default=Path("out/bench.json"), help="JSON output")


def add_calibrate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "fit", type=Path, nargs="+", help="results.json of in-process slloc eval runs to fit on"
    )
    parser.add_argument(
        "--held-out",
        type=Path,
        action="append",
        default=[],
        help="results.json of a run not used to fit, for the reported precision (repeatable)",
    )
    parser.add_argument(
        "--l2",
        type=float,
        help="L2 penalty of the weights (default: cross-validated on the fit runs)",
    )
    parser.add_argument(
        "--features",
        help="comma-separated confidence features to fit (default: all of "
        "services.confidence.model.FEATURES)",
    )
    parser.add_argument("--note", default="", help="what the runs were, for the file")
    parser.add_argument("--out", type=Path, help="write the coefficients file here")


def add_self_evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--url", required=True, help="the server")
    parser.add_argument("--api-key", help="X-API-Key (an admin key to start one)")
    parser.add_argument("--map", required=True, help="the map's name or id")
    parser.add_argument(
        "--configurations",
        help="comma-separated feature configurations (default: every one the server can run)",
    )
    parser.add_argument("--sample-size", type=int, help="references held out (default 30)")
    parser.add_argument(
        "--holdout-radius", type=float, help="hold out the references within this distance too"
    )
    parser.add_argument("--top-k", type=int, help="references retrieved per held-out query")
    parser.add_argument(
        "--latest", action="store_true", help="print the latest finished one; start nothing"
    )
    parser.add_argument(
        "--timeout", type=float, default=3600.0, help="seconds to wait for it (default 3600)"
    )
    parser.add_argument("--json", type=Path, help="also write the evaluation as JSON here")
