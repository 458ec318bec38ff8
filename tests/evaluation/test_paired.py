"""``auto`` against each estimator on the same queries (``tools.evaluation.paired``), on
hand-made records whose sign-test values are worked out by hand."""

from __future__ import annotations

import math

import pytest

from tests.evaluation.records import hand_made
from tools.evaluation.metrics import QueryRecord
from tools.evaluation.paired import paired_against_auto
from tools.evaluation.report import paired_table

THRESHOLDS = ((0.05, 5.0), (0.25, 2.0))


def _record(config: str, query: str, pos: float, rot: float, **flags: bool) -> QueryRecord:
    return hand_made(config, query, pos, rot, **flags)


def _records() -> list[QueryRecord]:
    records = []
    for i in range(4):  # auto alone within 5 cm: four queries
        records += [_record("x/auto", f"a{i}", 0.02, 1.0), _record("x/e5p1", f"a{i}", 0.08, 1.0)]
    # e5p1 alone within 5 cm, and within (25 cm, 2°) where auto is 3° off
    records += [_record("x/auto", "b", 0.06, 3.0), _record("x/e5p1", "b", 0.03, 1.0)]
    # both right: no evidence either way
    records += [_record("x/auto", "c", 0.01, 0.5), _record("x/e5p1", "c", 0.01, 0.5)]
    # auto failed, e5p1 right
    records += [_record("x/auto", "d", math.inf, math.inf), _record("x/e5p1", "d", 0.2, 1.0)]
    # not compared: an unrelated image, a wrong-intrinsics copy, another feature set
    records += [_record("x/e5p1", "u", 0.01, 0.1, unrelated=True)]
    records += [_record("x/e5p1", "w", 0.01, 0.1, wrong_intrinsics=True)]
    records += [_record("y/e5p1", "a0", 0.01, 0.1)]
    return records


def test_counts_and_sign_test() -> None:
    paired = paired_against_auto(_records(), THRESHOLDS)
    assert list(paired) == ["x/auto"] and list(paired["x/auto"]) == ["x/e5p1"]
    cells = paired["x/auto"]["x/e5p1"]
    five = cells["5cm_5deg"]
    assert (five["auto_only"], five["other_only"]) == (4, 1)  # a0-a3 / b (d's is 20 cm off)
    # two-sided: P(X ≤ 1) + P(X ≥ 4) for X ~ Binomial(5, 1/2) = (1 + 5 + 5 + 1) / 32
    assert five["p_value"] == pytest.approx(12 / 32)
    wide = cells["25cm_2deg"]
    assert (wide["auto_only"], wide["other_only"]) == (0, 2)  # a0-a3 both within / b (3°), d
    assert wide["p_value"] == pytest.approx(0.5)
    table = "\n".join(paired_table({"x/auto": {"paired": paired["x/auto"]}}, THRESHOLDS))
    assert "| x/auto | x/e5p1 | 4 / 1 (p 0.38) | 0 / 2 (p 0.50) |" in table


def test_a_lopsided_gap_is_unlikely_by_chance() -> None:
    records = []
    for i in range(8):
        records += [_record("x/auto", f"q{i}", 0.02, 1.0), _record("x/sift", f"q{i}", 1.0, 9.0)]
    cell = paired_against_auto(records, THRESHOLDS)["x/auto"]["x/sift"]["5cm_5deg"]
    assert (cell["auto_only"], cell["other_only"]) == (8, 0)
    assert cell["p_value"] == pytest.approx(2 / 2**8)


def test_nothing_to_compare_without_auto() -> None:
    records = [r for r in _records() if not r.config.endswith("/auto")]
    assert paired_against_auto(records, THRESHOLDS) == {}
    assert paired_table({"x/e5p1": {}}, THRESHOLDS) == []
