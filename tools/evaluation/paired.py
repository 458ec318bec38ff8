"""``auto`` against each other estimator on the same queries: how many queries only one of the
two got within each threshold, and the two-sided sign test of those counts (SciPy's exact
binomial test at one half): the chance of a gap at least as large if neither were better."""

from __future__ import annotations

from typing import Any

from scipy.stats import binomtest

from services.self_evaluation.summary import recall_key
from tools.evaluation.metrics import QueryRecord, within

CHOOSER = "auto"


def paired_against_auto(
    records: list[QueryRecord], thresholds: tuple[tuple[float, float], ...]
) -> dict[str, dict[str, dict[str, dict[str, Any]]]]:
    """For every ``features/auto`` configuration, each other estimator of the same features:
    per threshold, ``auto_only`` and ``other_only`` (queries only that one got within it) and
    ``p_value``, over the queries both were asked that have ground truth (unrelated images
    and wrong-intrinsics copies left out); a failure is within no threshold."""
    by_config: dict[str, dict[str, QueryRecord]] = {}
    for r in records:
        if not r.unrelated and not r.wrong_intrinsics:
            by_config.setdefault(r.config, {})[r.query] = r
    paired: dict[str, dict[str, dict[str, dict[str, Any]]]] = {}
    for config, chosen in by_config.items():
        features, _, estimator = config.rpartition("/")
        if estimator != CHOOSER:
            continue
        against: dict[str, dict[str, dict[str, Any]]] = {}
        for other_config, other in by_config.items():
            if other_config == config or other_config.rpartition("/")[0] != features:
                continue
            common = chosen.keys() & other.keys()
            cells: dict[str, dict[str, Any]] = {}
            for m, d in thresholds:
                auto_only = sum(within(chosen[q], m, d) > within(other[q], m, d) for q in common)
                other_only = sum(within(other[q], m, d) > within(chosen[q], m, d) for q in common)
                discordant = auto_only + other_only
                cells[recall_key(m, d)] = {
                    "auto_only": auto_only,
                    "other_only": other_only,
                    "p_value": binomtest(auto_only, discordant).pvalue if discordant else 1.0,
                }
            against[other_config] = cells
        paired[config] = against
    return paired
