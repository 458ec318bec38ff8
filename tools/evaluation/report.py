"""Evaluation outputs: Markdown tables (accuracy, stage timings, the confidence's precision and
recall, ``auto``'s choices and its paired comparison with each estimator), a JSON file, and
PNG plots (cumulative error curves per configuration, per-stage median times, the
confidence's precision/recall curve)."""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from services.self_evaluation.summary import recall_key
from tools.evaluation.confidence_curve import REPORTED_THRESHOLDS, TARGET, curve_of
from tools.evaluation.metrics import (
    CONFIDENT,
    STAGES,
    WRONG_DEG,
    WRONG_M,
    QueryRecord,
)

PLOT_STAGES = ("decode", "extract", "retrieve", "match", "estimate")


def _num(value: float, scale: float = 1.0, digits: int = 1) -> str:
    return f"{value * scale:.{digits}f}" if math.isfinite(value) else "–"


def markdown_tables(
    summaries: dict[str, dict[str, Any]], thresholds: tuple[tuple[float, float], ...]
) -> str:
    """Accuracy table and timing table, one row per configuration."""
    recall_heads = [f"({m * 100:g} cm, {d:g}°)" for m, d in thresholds]
    head = [
        "configuration",
        "localized",
        *recall_heads,
        "median / p90 position (cm)",
        "median / p90 rotation (°)",
        "failures",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for config, s in summaries.items():
        pos, rot = s["position_error_m"], s["rotation_error_deg"]
        failures = ", ".join(f"{k} {v}" for k, v in sorted(s["failures"].items())) or "–"
        lines.append(
            "| "
            + " | ".join(
                [
                    config,
                    f"{s['localized']}/{s['queries']}",
                    *(f"{s['recall'][recall_key(m, d)] * 100:.1f} %" for m, d in thresholds),
                    f"{_num(pos['median'], 100)} / {_num(pos['p90'], 100)}",
                    f"{_num(rot['median'], 1, 2)} / {_num(rot['p90'], 1, 2)}",
                    failures,
                ]
            )
            + " |"
        )
    stage_head = ["configuration", *(f"{stage} ms" for stage in STAGES)]
    lines += ["", "Stage timings, median / p90 (`client` = wall time seen by the evaluator):", ""]
    lines += ["| " + " | ".join(stage_head) + " |", "|" + "---|" * len(stage_head)]
    for config, s in summaries.items():
        t = s["timings_ms"]
        cells = [f"{_num(t[st]['median'], 1, 0)} / {_num(t[st]['p90'], 1, 0)}" for st in STAGES]
        lines.append("| " + " | ".join([config, *cells]) + " |")
    extra = [
        f"| {config} | {s['localizable_queries']} | "
        f"{s['localizable_recall_10cm_5deg'] * 100:.1f} % | {s['retrieval_covered_queries']} | "
        f"{s['retrieval_recall'] * 100:.1f} % | "
        + (f"{s['unrelated_accepted']}/{s['unrelated_queries']}" if s["unrelated_queries"] else "–")
        + " |"
        for config, s in summaries.items()
    ]
    lines += [
        "",
        "Localizable queries have a reference within 0.3 m and 15°; retrieval recall counts "
        "queries with a reference within 0.5 m and 30° whose retrieved set holds one:",
        "",
        "| configuration | localizable | their recall (10 cm, 5°) | covered | retrieval recall "
        "| unrelated accepted |",
        "|---|---|---|---|---|---|",
        *extra,
        "",
        f"Answers with confidence > {CONFIDENT:g}, and those of them more than "
        f"{WRONG_M * 100:g} cm or {WRONG_DEG:g}° off: "
        + ", ".join(
            f"{config} {s['confident']} / {s['confident_wrong']} wrong"
            for config, s in summaries.items()
        ),
        "",
        "Answers withheld below `min_confidence` (`low_confidence`, the pose as `candidate`), "
        f"and those of them within {WRONG_M * 100:g} cm and {WRONG_DEG:g}°: "
        + ", ".join(
            f"{config} {s['withheld']} / {s['withheld_right']} right"
            for config, s in summaries.items()
        ),
    ]
    if any(s.get("second_opinions") for s in summaries.values()):
        lines += [
            "",
            "Second opinions (the map's configuration found no answer; `--second-opinion`): "
            f"asked, localized by it, of those within {WRONG_M * 100:g} cm and {WRONG_DEG:g}°; "
            "withheld poses that agreed with the map's, localized so, of those right; "
            "its median time: "
            + ", ".join(
                f"{config} {s['second_opinions']}, {s['second_opinions_localized']}, "
                f"{s['second_opinions_right']} right; {s.get('second_opinions_agreed', 0)}, "
                f"{s.get('agreed_localized', 0)}, {s.get('agreed_right', 0)} right; "
                f"{s['second_opinion_ms'] or 0:.0f} ms"
                for config, s in summaries.items()
                if s.get("second_opinions")
            ),
        ]
    lines += ["", *confidence_table(summaries)]
    lines += choices_table(summaries, thresholds)
    lines += paired_table(summaries, thresholds)
    return "\n".join(lines) + "\n"


def choices_table(
    summaries: dict[str, dict[str, Any]], thresholds: tuple[tuple[float, float], ...]
) -> list[str]:
    """Whose poses the configurations that choose an estimator per query (``auto``) answered
    with, and how many of each were within each threshold; nothing without such a one."""
    rows = []
    for config, s in summaries.items():
        asked = config.rsplit("/", 1)[-1]
        if set(s["choices"]) <= {asked}:
            continue
        for name, chosen in s["choices"].items():
            recall = chosen["recall"]
            cells = [f"{recall[recall_key(m, d)] * 100:.1f} %" for m, d in thresholds]
            rows.append(f"| {config} | {name} | {chosen['answers']} | " + " | ".join(cells) + " |")
    return _table(
        "Choices: the localized answers by the estimator whose pose each is, and the share of "
        "them within each threshold:",
        ["configuration", "pose of", "answers", *_threshold_heads(thresholds)],
        rows,
    )


def confidence_table(summaries: dict[str, dict[str, Any]]) -> list[str]:
    """Precision / recall / accepted answers of "confidence > t" per configuration (see
    ``tools.evaluation.confidence_curve``); queries with wrong intrinsics and unrelated
    images take part."""
    heads = [f"conf > {t:g}" for t in REPORTED_THRESHOLDS]
    lines = [
        f"Confidence: precision / recall / accepted answers of confidence > t, correct = within "
        f"({TARGET[0] * 100:g} cm, {TARGET[1]:g}°); wrong-intrinsics queries and unrelated "
        "images included:",
        "",
        "| configuration | " + " | ".join(heads) + " | wrong intrinsics accepted |",
        "|---|" + "---|" * (len(heads) + 1),
    ]
    for config, s in summaries.items():
        cells = [
            f"{c['precision'] * 100:.1f} % / {c['recall'] * 100:.1f} % / {c['accepted']}"
            for c in (s["confidence"][f"> {t:g}"] for t in REPORTED_THRESHOLDS)
        ]
        wrong = (
            f"{s['wrong_intrinsics_accepted']}/{s['wrong_intrinsics_queries']}"
            if s["wrong_intrinsics_queries"]
            else "–"
        )
        lines.append("| " + " | ".join([config, *cells, wrong]) + " |")
    return lines


def paired_table(
    summaries: dict[str, dict[str, Any]], thresholds: tuple[tuple[float, float], ...]
) -> list[str]:
    """``auto`` against each other estimator (``tools.evaluation.paired``); nothing without
    ``auto`` and another estimator."""
    rows = []
    for config, s in summaries.items():
        for other, cells in s.get("paired", {}).items():
            texts = []
            for m, d in thresholds:
                cell = cells[recall_key(m, d)]
                texts.append(
                    f"{cell['auto_only']} / {cell['other_only']} (p {cell['p_value']:.2f})"
                )
            rows.append(f"| {config} | {other} | " + " | ".join(texts) + " |")
    return _table(
        "`auto` against each estimator on the same queries: those only `auto` got within the "
        "threshold / those only the other got (two-sided sign test: the chance of a gap at "
        "least as large if neither were better):",
        ["configuration", "against", *_threshold_heads(thresholds)],
        rows,
    )


def _threshold_heads(thresholds: tuple[tuple[float, float], ...]) -> list[str]:
    return [f"({m * 100:g} cm, {d:g}°)" for m, d in thresholds]


def _table(intro: str, heads: list[str], rows: list[str]) -> list[str]:
    """A titled Markdown table after a blank line; nothing without rows."""
    if not rows:
        return []
    return ["", intro, "", "| " + " | ".join(heads) + " |", "|" + "---|" * len(heads), *rows]


def _json_safe(value: Any) -> Any:
    """Non-finite floats (failed queries' errors) become null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def write_json(
    path: Path,
    meta: dict[str, Any],
    summaries: dict[str, dict[str, Any]],
    records: list[QueryRecord],
) -> None:
    payload = {"meta": meta, "summaries": summaries, "queries": [asdict(r) for r in records]}
    path.write_text(json.dumps(_json_safe(payload), indent=1))


def write_plots(
    out_dir: Path,
    summaries: dict[str, dict[str, Any]],
    records: list[QueryRecord],
) -> list[Path]:
    """``errors.png`` (cumulative position and rotation error per configuration, up to 50 cm
    and 10°) and ``timings.png`` (median time per stage, stacked)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    configs = list(summaries)
    fig, (ax_pos, ax_rot) = plt.subplots(1, 2, figsize=(12, 4.5))
    for config in configs:
        posed = [r for r in records if r.config == config and not r.unrelated]
        if not posed:
            continue
        fractions = np.arange(1, len(posed) + 1) / len(posed)
        for ax, values, scale in (
            (ax_pos, [r.position_error_m for r in posed], 100.0),
            (ax_rot, [r.rotation_error_deg for r in posed], 1.0),
        ):
            ax.step(np.sort(np.asarray(values)) * scale, fractions, where="post", label=config)
    ax_pos.set(
        xlabel="position error (cm)", ylabel="fraction of queries", xlim=(0, 50), ylim=(0, 1)
    )
    ax_rot.set(xlabel="rotation error (°)", xlim=(0, 10), ylim=(0, 1))
    for ax in (ax_pos, ax_rot):
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
    ax_rot.legend(fontsize=8, loc="lower right")
    fig.suptitle("Cumulative error (failures never reach 1)")
    fig.tight_layout()
    errors_png = out_dir / "errors.png"
    fig.savefig(errors_png, dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(max(6.0, 1.0 + 0.9 * len(configs)), 4.5))
    bottom = np.zeros(len(configs))
    for stage in PLOT_STAGES:
        heights = np.array(
            [np.nan_to_num(summaries[c]["timings_ms"][stage]["median"]) for c in configs]
        )
        ax.bar(configs, heights, bottom=bottom, label=stage)
        bottom += heights
    ax.set(ylabel="median time (ms)", title="Per-stage median time")
    ax.tick_params(axis="x", rotation=30)
    ax.legend(fontsize=8)
    fig.tight_layout()
    timings_png = out_dir / "timings.png"
    fig.savefig(timings_png, dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6.5, 5))
    for config in configs:
        curve = curve_of([r for r in records if r.config == config])
        line = ax.step(curve.recall, curve.precision, where="post", label=config)[0]
        precision, recall, _ = curve.at(0.8)
        ax.plot([recall], [precision], "o", color=line.get_color())
    ax.set(
        xlabel=f"recall (correct within {TARGET[0] * 100:g} cm, {TARGET[1]:g}°)",
        ylabel="precision",
        xlim=(0, 1),
        ylim=(0, 1.02),
        title="Accepting confidence > t for every t (dot: t = 0.8)",
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    confidence_png = out_dir / "confidence.png"
    fig.savefig(confidence_png, dpi=100)
    plt.close(fig)
    return [errors_png, timings_png, confidence_png]
