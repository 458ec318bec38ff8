"""The report of ``auto``'s choices: whose pose each localized answer is, and how many of each
were within each threshold, on hand-made records."""

from __future__ import annotations

import math

from tests.evaluation.records import hand_made
from tools.evaluation.metrics import QueryRecord, summarize
from tools.evaluation.report import choices_table

THRESHOLDS = ((0.05, 5.0), (0.25, 2.0))


def _record(config: str, used: str | None, pos: float, rot: float) -> QueryRecord:
    return hand_made(config, "q", pos, rot, estimator_used=used)


def test_choices_count_each_estimators_answers_and_their_recall() -> None:
    records = [
        _record("sift/auto", "local_tri_all", 0.02, 1.0),
        _record("sift/auto", "local_tri_all", 0.04, 3.0),  # 3°: not within (25 cm, 2°)
        _record("sift/auto", "local_tri_all", 0.50, 1.0),
        _record("sift/auto", "e5p1", 0.10, 1.0),
        _record("sift/auto", "e5p1", math.inf, math.inf),  # not localized: no choice
    ]
    chosen = summarize(records, THRESHOLDS)["choices"]
    assert list(chosen) == ["local_tri_all", "e5p1"]  # most answers first
    assert chosen["local_tri_all"]["answers"] == 3
    assert chosen["local_tri_all"]["recall"] == {"5cm_5deg": 2 / 3, "25cm_2deg": 1 / 3}
    assert chosen["e5p1"] == {"answers": 1, "recall": {"5cm_5deg": 0.0, "25cm_2deg": 1.0}}


def test_the_table_lists_only_configurations_that_choose() -> None:
    summaries = {
        "sift/e5p1": summarize([_record("sift/e5p1", "e5p1", 0.02, 1.0)], THRESHOLDS),
        "sift/auto": summarize(
            [
                _record("sift/auto", "local_tri_all", 0.02, 1.0),
                _record("sift/auto", "e5p1", 0.10, 1.0),
            ],
            THRESHOLDS,
        ),
    }
    table = "\n".join(choices_table(summaries, THRESHOLDS))
    assert "| sift/auto | local_tri_all | 1 | 100.0 % | 100.0 % |" in table
    assert "| sift/auto | e5p1 | 1 | 0.0 % | 100.0 % |" in table
    assert "sift/e5p1" not in table
    single = {"sift/e5p1": summaries["sift/e5p1"]}
    assert choices_table(single, THRESHOLDS) == []
