"""``slloc eval``: the command (progress on stderr, Markdown tables on stdout)."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

from app.settings import get_settings
from services.components import resolve_features
from services.estimators.registry import estimator_names
from services.features.configs import AUTO, feature_config_names
from tools.evaluation.datasets import open_dataset
from tools.evaluation.evaluate import (
    MAX_QUERY_SCALE,
    MIN_QUERY_SCALE,
    EvalOptions,
    run_evaluation,
    write_outputs,
)
from tools.evaluation.metrics import DEFAULT_THRESHOLDS
from tools.evaluation.runner import HttpRunner, InProcessRunner, Runner
from tools.evaluation.split import split_dataset


def _names(value: str, known: list[str], what: str) -> list[str]:
    names = known if value.strip() == "all" else [v.strip() for v in value.split(",") if v.strip()]
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise ValueError(f"unknown {what} {unknown}; known: {', '.join(known)}")
    return names


def _thresholds(values: list[str] | None) -> tuple[tuple[float, float], ...]:
    if not values:
        return DEFAULT_THRESHOLDS
    pairs = []
    for value in values:
        metres, _, degrees = value.partition(",")
        pairs.append((float(metres), float(degrees)))
    return tuple(pairs)


def _images_in(folder: Path | None) -> list[Path]:
    """The JPEG and PNG files of ``folder``, sorted (none without a folder).

    Raises:
        ValueError: ``folder`` holds none.
    """
    if folder is None:
        return []
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    if not images:
        raise ValueError(f"no JPEG or PNG images in {folder}")
    return images


def _log(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def eval_main(args: argparse.Namespace) -> int:
    logging.getLogger().setLevel(logging.WARNING)  # per-image INFO lines would drown progress
    try:
        dataset = open_dataset(args.dataset, args.images, args.poses)
        split = split_dataset(dataset, args.references, args.queries)
        estimators = _names(args.estimators, estimator_names(), "estimators")
        settings = get_settings()
        requested = _names(args.features, [AUTO, *feature_config_names()], "features")
        features = list(
            dict.fromkeys(  # auto = what the server runs with (SLLOC_FEATURES)
                resolve_features(settings.models_dir, settings.features if n == AUTO else n)
                for n in requested
            )
        )
        thresholds = _thresholds(args.threshold)
        if args.max_queries is not None and args.max_queries < 1:
            raise ValueError("--max-queries must be at least 1")
        if args.wrong_focal < 0:
            raise ValueError("--wrong-focal must not be negative")
        if not MIN_QUERY_SCALE <= args.query_scale <= MAX_QUERY_SCALE:
            raise ValueError(
                f"--query-scale must be within {MIN_QUERY_SCALE}-{MAX_QUERY_SCALE}, "
                f"got {args.query_scale:g}"
            )
        unrelated_images = _images_in(args.unrelated_images)
    except (OSError, ValueError) as exc:
        print(f"slloc eval: {exc}", file=sys.stderr)
        return 2
    options = EvalOptions(
        estimators=estimators,
        top_k=args.top_k,
        max_error_px=args.max_error_px,
        use_depth=not args.no_depth,
        unrelated=args.unrelated,
        max_queries=args.max_queries,
        wrong_focal=args.wrong_focal,
        unrelated_seed=args.unrelated_seed,
        unrelated_images=unrelated_images,
        send_intrinsics=not args.no_intrinsics,
        query_scale=args.query_scale,
    )
    map_features = {
        key: value
        for key, value in (("max_keypoints", args.max_keypoints), ("max_side", args.max_side))
        if value is not None
    }
    if args.second_opinion and args.url:
        raise SystemExit("--second-opinion is in process only (a server has SLLOC_SECOND_OPINION)")
    if args.second_opinion and args.second_opinion not in feature_config_names():
        raise SystemExit(f"--second-opinion: unknown {args.second_opinion}")
    if args.map_preset and not args.url:
        raise SystemExit("--map-preset needs --url (in process, --features names each run's)")
    factories: list[Callable[[], Runner]]
    if args.url:
        factories = [
            partial(
                HttpRunner,
                args.url,
                args.api_key,
                f"slloc-eval-{dataset.name}",
                args.keep_map,
                features={**map_features, "preset": args.map_preset}
                if args.map_preset
                else map_features,
            )
        ]
    else:
        factories = [
            partial(
                InProcessRunner,
                name,
                settings.models_dir,
                **map_features,
                second_opinion=args.second_opinion if args.second_opinion != name else "",
            )
            for name in features
        ]
    _log(
        f"{dataset.name}: {len(split.references)} references, {len(split.queries)} queries, "
        f"estimators {', '.join(estimators)}, "
        + (f"server {args.url}" if args.url else f"features {', '.join(features)}, in process")
    )
    start = time.perf_counter()
    evaluation = run_evaluation(split, factories, options, _log)
    meta = {
        "dataset": str(args.dataset),
        "mode": "http" if args.url else "in-process",
        "references": len(split.references),
        "queries": len(split.queries[: args.max_queries]),
        "estimators": estimators,
        "features": None if args.url else features,
        "top_k": args.top_k,
        "map_features": map_features,
        "max_error_px": args.max_error_px,
        "intrinsics": not args.no_intrinsics,
        "query_scale": args.query_scale,
        "second_opinion": args.second_opinion or None,
        "thresholds": thresholds,
        "seconds": time.perf_counter() - start,
    }
    write_outputs(evaluation, args.out, meta, thresholds)
    print(evaluation.markdown)
    _log(f"wrote {', '.join(str(p) for p in evaluation.files)} in {meta['seconds']:.0f} s")
    if evaluation.error is not None:
        return 1
    return 130 if evaluation.interrupted else 0
