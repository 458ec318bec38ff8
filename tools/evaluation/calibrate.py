"""``slloc calibrate``: fit the confidence model (``services.confidence.model``) on the localized
answers of ``slloc eval`` runs (their ``results.json``, in-process runs: they carry the stats),
report its precision/recall on held-out runs, and write the coefficients file.

The model is an L2-regularised logistic regression fitted by Newton's method in numpy; the
weights of ``MONOTONE_INCREASING`` features are kept >= 0 (a feature whose weight would turn
negative is dropped and the rest refitted), so more evidence never lowers the confidence. The
penalty is chosen by cross-validation on the fit runs (folds by query, so the answers of one
query never sit on both sides), never on the held-out runs.
"""

from __future__ import annotations

import argparse
import json
import sys
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import date
from pathlib import Path
from typing import Any

import numpy as np

from services.confidence.model import (
    FEATURES,
    MONOTONE_INCREASING,
    ConfidenceModel,
    base_estimator,
    feature_vector,
)
from services.estimators.options import UncertaintyOptions
from services.estimators.uncertainty import PoseUncertainty, capped_confidence
from services.types import BoolArray, FloatArray
from tools.evaluation.confidence_curve import TARGET, ConfidenceCurve, precision_recall


@dataclass(frozen=True)
class Samples:
    """Answers of eval runs: every answer (for the curves), the localized ones fitted.

    Attributes:
        stats: each answer's stats.
        estimators: the estimator whose answer it is, the name the service scores it with
            (for ``auto``, the estimator it chose: ``estimator_used``).
        localized: (N,) the answer has a pose.
        correct: (N,) its pose is within the target.
        unrelated: (N,) the query is an image of another scene (no ground truth).
        wrong_intrinsics: (N,) the query was sent with a wrong focal length.
        queries: each answer's query, as ``<results file>:<query name>``.
        configs: each answer's estimator as asked (``auto`` for all of auto's answers).
    """

    stats: list[dict[str, float]]
    estimators: list[str]
    localized: BoolArray
    correct: BoolArray
    unrelated: BoolArray
    wrong_intrinsics: BoolArray
    queries: list[str]
    configs: list[str]

    @property
    def positives(self) -> int:
        """Answers to queries with ground truth."""
        return int((~self.unrelated).sum())


def load_samples(paths: list[Path], target: tuple[float, float] = TARGET) -> Samples:
    """The answers in the ``results.json`` files of in-process ``slloc eval`` runs."""
    stats, estimators, localized, correct, unrelated, wrong = [], [], [], [], [], []
    queries: list[str] = []
    configs: list[str] = []
    max_m, max_deg = target
    for path in paths:
        for q in json.loads(path.read_text())["queries"]:
            queries.append(f"{path}:{q['query']}")
            pos, rot = q["position_error_m"], q["rotation_error_deg"]
            stats.append({k: float(v) for k, v in q.get("stats", {}).items()})
            configs.append(q["config"].split("/")[-1])
            estimators.append(q.get("estimator_used") or configs[-1])
            localized.append(bool(q["localized"]))
            correct.append(
                bool(q["localized"])
                and not q["unrelated"]
                and pos is not None
                and pos <= max_m
                and rot <= max_deg
            )
            unrelated.append(bool(q["unrelated"]))
            wrong.append(bool(q.get("wrong_intrinsics", False)))
    return Samples(
        stats,
        estimators,
        np.array(localized, bool),
        np.array(correct, bool),
        np.array(unrelated, bool),
        np.array(wrong, bool),
        queries,
        configs,
    )


def fit_logistic(
    x: FloatArray,
    y: BoolArray,
    l2: float = 1.0,
    nonnegative: BoolArray | None = None,
    iterations: int = 100,
) -> tuple[FloatArray, float]:
    """Weights and intercept minimising the logistic loss + ``l2``/2·|w|² (intercept free).

    Args:
        x: (N, F) features; y: (N,) labels.
        nonnegative: (F,) weights kept >= 0 (active set: a negative one is fixed at 0 and the
            others refitted).
    Returns:
        (F,) weights and the intercept.
    """
    f = x.shape[1]
    free = np.ones(f, bool)
    keep = np.zeros(f, bool) if nonnegative is None else nonnegative
    while True:
        w = _newton(x[:, free], y.astype(np.float64), l2, iterations)
        weights = np.zeros(f)
        weights[free] = w[1:]
        negative = free & keep & (weights < 0.0)
        if not negative.any():
            return weights, float(w[0])
        free &= ~negative


def _newton(x: FloatArray, y: FloatArray, l2: float, iterations: int) -> FloatArray:
    """(1 + F,) intercept then weights; the intercept is not penalised."""
    a = np.concatenate([np.ones((x.shape[0], 1)), x], axis=1)
    penalty = np.full(a.shape[1], l2)
    penalty[0] = 0.0
    w = np.zeros(a.shape[1])
    for _ in range(iterations):
        p = 1.0 / (1.0 + np.exp(-np.clip(a @ w, -30.0, 30.0)))
        gradient = a.T @ (p - y) + penalty * w
        hessian = (a * (p * (1.0 - p))[:, None]).T @ a + np.diag(penalty + 1e-9)
        step = np.linalg.solve(hessian, gradient)
        w -= step
        if float(np.abs(step).max()) < 1e-10:
            break
    return w


L2_GRID = (0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0)


def subset(samples: Samples, keep: BoolArray) -> Samples:
    """The answers where (N,) ``keep`` holds."""
    index = np.flatnonzero(keep)
    return Samples(
        [samples.stats[i] for i in index],
        [samples.estimators[i] for i in index],
        samples.localized[index],
        samples.correct[index],
        samples.unrelated[index],
        samples.wrong_intrinsics[index],
        [samples.queries[i] for i in index],
        [samples.configs[i] for i in index],
    )


def cross_validated_l2(
    samples: Samples,
    folds: int = 5,
    grid: tuple[float, ...] = L2_GRID,
    features: Sequence[str] = tuple(FEATURES),
) -> float:
    """The penalty of ``grid`` with the best mean log-likelihood of the localized answers of
    held-in folds; folds by query (a hash of its name, so the choice is reproducible)."""
    fold = np.array([zlib.crc32(q.encode()) % folds for q in samples.queries])
    best, best_score = grid[0], -np.inf
    for l2 in grid:
        total = 0.0
        for k in range(folds):
            train, test = subset(samples, fold != k), subset(samples, fold == k)
            if not test.localized.any() or train.correct.all() or not train.correct.any():
                continue
            model = fit_model(train, l2, features=features)
            p = np.array(
                [
                    model.confidence(s, e)
                    for s, e, ok in zip(test.stats, test.estimators, test.localized, strict=True)
                    if ok
                ]
            )
            y = test.correct[test.localized]
            p = np.clip(p, 1e-9, 1 - 1e-9)
            total += float(np.sum(np.where(y, np.log(p), np.log(1 - p))))
        if total > best_score:
            best, best_score = l2, total
    return best


def fit_model(
    samples: Samples,
    l2: float = 1.0,
    description: str = "",
    features: Sequence[str] = tuple(FEATURES),
) -> ConfidenceModel:
    """The confidence model of the localized answers of ``samples`` over ``features`` (keys
    of ``FEATURES``)."""
    names = tuple(features)
    chosen = np.flatnonzero(samples.localized)
    raw = np.stack([feature_vector(samples.stats[i], names) for i in chosen])
    mean, scale = raw.mean(axis=0), raw.std(axis=0)
    scale = np.where(scale > 1e-9, scale, 1.0)
    estimators = sorted({base_estimator(samples.estimators[i]) for i in chosen})
    one_hot = np.array(
        [[base_estimator(samples.estimators[i]) == e for e in estimators] for i in chosen],
        np.float64,
    ).reshape(len(chosen), len(estimators))
    x = np.concatenate([(raw - mean) / scale, one_hot], axis=1)
    monotone = np.array([n in MONOTONE_INCREASING for n in names] + [False] * len(estimators))
    weights, intercept = fit_logistic(x, samples.correct[chosen], l2, monotone)
    return ConfidenceModel(
        features=names,
        mean=tuple(float(v) for v in mean),
        scale=tuple(float(v) for v in scale),
        weights=tuple(float(v) for v in weights[: len(names)]),
        intercept=intercept,
        estimator_offsets={
            e: float(v) for e, v in zip(estimators, weights[len(names) :], strict=True)
        },
        target_position_m=TARGET[0],
        target_rotation_deg=TARGET[1],
        description=description,
    )


def answered_confidence(model: ConfidenceModel, stats: dict[str, float], estimator: str) -> float:
    """The confidence the service answers for a localized result with ``stats``: the model's,
    capped by the pose uncertainty and ``auto``'s disagreement in the stats
    (``capped_confidence``, default options; the focal length counts as estimated when the
    stats have ``focal_px``)."""
    uncertainty = None
    if "position_sigma_m" in stats and "rotation_sigma_deg" in stats:
        # answers recorded before the points' own uncertainty was reported cap on the pose's
        # given the points
        uncertainty = PoseUncertainty(
            stats.get("structure_position_sigma_m", stats["position_sigma_m"]),
            stats.get("structure_rotation_sigma_deg", stats["rotation_sigma_deg"]),
            int(stats.get("uncertainty_points", 0)),
            stats.get("uncertainty_sigma_px", 0.0),
            stats["position_sigma_m"],
            stats["rotation_sigma_deg"],
        )
    return capped_confidence(
        model.confidence(stats, estimator),
        uncertainty,
        UncertaintyOptions(),
        "focal_px" in stats,
        stats,
    )


def curve_with(model: ConfidenceModel, samples: Samples) -> ConfidenceCurve:
    """The precision/recall curve of ``samples`` under the confidence the service would answer
    with ``model`` (``answered_confidence``)."""
    confidence = np.array(
        [
            answered_confidence(model, s, e) if ok else 0.0
            for s, e, ok in zip(samples.stats, samples.estimators, samples.localized, strict=True)
        ]
    )
    return precision_recall(confidence, samples.correct, samples.localized, samples.positives)


def _report(name: str, model: ConfidenceModel, samples: Samples) -> dict[str, Any]:
    curve = curve_with(model, samples)
    out: dict[str, Any] = {"answers": len(samples.stats), "localized": int(samples.localized.sum())}
    out["correct"] = int(samples.correct.sum())
    for t in (0.5, 0.8, 0.9):
        precision, recall, accepted = curve.at(t)
        out[f"> {t:g}"] = {"precision": precision, "recall": recall, "accepted": accepted}
    print(
        f"{name}: {out['answers']} answers, {out['localized']} localized, {out['correct']} "
        "correct; "
        + "; ".join(
            f"conf {k}: precision {v['precision'] * 100:.1f} %, recall {v['recall'] * 100:.1f} "
            f"%, {v['accepted']} accepted"
            for k, v in out.items()
            if k.startswith(">")
        )
    )
    return out


def calibrate_main(args: argparse.Namespace) -> int:
    try:
        samples = load_samples(args.fit)
        held_out = load_samples(args.held_out) if args.held_out else None
    except (OSError, ValueError, KeyError) as exc:
        print(f"slloc calibrate: {exc}", file=sys.stderr)
        return 2
    features = tuple(FEATURES)
    if args.features:
        features = tuple(f.strip() for f in args.features.split(",") if f.strip())
        unknown = [f for f in features if f not in FEATURES]
        if unknown or not features:
            print(
                f"slloc calibrate: unknown features {unknown}; known: {', '.join(FEATURES)}",
                file=sys.stderr,
            )
            return 2
    if samples.correct.all() or not samples.correct[samples.localized].any():
        print("slloc calibrate: the fit needs correct and wrong answers", file=sys.stderr)
        return 2
    description = (
        f"fitted {date.today().isoformat()} by slloc calibrate on "
        f"{int(samples.localized.sum())} localized answers"
        + (f" ({args.note})" if args.note else "")
    )
    l2 = cross_validated_l2(samples, features=features) if args.l2 is None else args.l2
    print(f"L2 penalty {l2:g}" + (" (cross-validated on the fit runs)" if args.l2 is None else ""))
    model = fit_model(samples, l2, f"{description}, L2 penalty {l2:g}", features)
    print(json.dumps(model.to_json(), indent=1))
    _report("fit", model, samples)
    if held_out is not None:
        _report("held out", model, held_out)
        if held_out.wrong_intrinsics.any():
            right = subset(held_out, ~held_out.wrong_intrinsics)
            _report("held out, right intrinsics", model, right)
        auto = np.array([c == "auto" for c in held_out.configs], bool)
        if auto.any() and not auto.all():
            _report("held out, auto's answers", model, subset(held_out, auto))
            if held_out.wrong_intrinsics[auto].any():
                auto_right = subset(held_out, auto & ~held_out.wrong_intrinsics)
                _report("held out, auto's answers, right intrinsics", model, auto_right)
    if args.out is not None:
        model.save(args.out)
        print(f"wrote {args.out}")
    return 0
