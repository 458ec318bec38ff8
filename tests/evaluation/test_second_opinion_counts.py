"""``slloc eval --second-opinion``: in process, a query the map's configuration does not
localize is localized again by the one named, and the summary counts those asked, answered and
right. The real engine on a rendered scene with exact poses (a sift map starved to 8 keypoints
an image, the exported XFeat second), and hand-made records."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from app.settings import get_settings
from services.components import missing_models
from tests.evaluation.records import hand_made
from tools.evaluation.confidence_curve import curve_of, curve_summary
from tools.evaluation.evaluate import localize_params
from tools.evaluation.metrics import QueryRecord, ReferencePoses, make_record, summarize
from tools.evaluation.report import markdown_tables
from tools.evaluation.runner import InProcessRunner
from tools.evaluation.split import Split

THRESHOLDS = ((0.05, 5.0), (0.25, 2.0))
SECOND = "xfeat"


def test_a_query_the_map_cannot_localize_is_answered_by_the_second(split: Split) -> None:
    models: Path = get_settings().models_dir
    if missing_models(models, SECOND):
        pytest.skip(f"{SECOND}'s models are not built (scripts/build_models.sh)")
    runner = InProcessRunner("sift", models, max_keypoints=8, second_opinion=SECOND)
    try:
        for image in split.references:
            runner.add_reference(image, None)
        runner.index_references(len(split.references))
        query = split.queries[0]
        params = localize_params(query.camera, "auto", top_k=10)
        [outcome] = runner.localize_each(query.image_path.read_bytes(), None, params, ["auto"])
    finally:
        runner.close()
    references = ReferencePoses.of({r.name: r.cam_from_world for r in split.references})
    record = make_record("sift/auto", query.name, outcome, query.cam_from_world, references)
    assert record.localized and record.position_error_m < 0.05
    summary = summarize([record], THRESHOLDS)
    assert summary["second_opinions"] == summary["second_opinions_localized"] == 1
    assert summary["second_opinions_right"] == 1 and summary["second_opinion_ms"] > 0.0


def test_the_summary_counts_the_second_opinions() -> None:
    def asked(pos: float, localized: bool, ms: float, agreed: bool = False) -> QueryRecord:
        stats = {
            "second_opinion_localized": float(localized and not agreed),
            "second_opinion_agreed": float(agreed),
            "second_opinion_ms": ms,
        }
        return hand_made(pos=pos, rot=1.0, localized=localized, stats=stats)

    records = [
        asked(0.1, True, 300.0),  # right
        asked(0.4, True, 500.0),  # answered, more than 25 cm off
        asked(math.inf, False, 100.0),  # asked, no answer either
        asked(0.05, True, 400.0, agreed=True),  # two withheld poses that agree, right
        asked(0.3, True, 350.0, agreed=True),  # the same, more than 25 cm off
        asked(math.inf, False, 200.0, agreed=True),  # agreed, still below min_confidence
        hand_made(pos=0.01, rot=0.1),  # answered by the map's own
    ]
    summary = summarize(records, THRESHOLDS)
    assert summary["second_opinions"] == 6
    assert summary["second_opinions_localized"] == 2
    assert summary["second_opinions_right"] == 1
    assert summary["second_opinions_agreed"] == 3
    assert summary["agreed_localized"] == 2 and summary["agreed_right"] == 1
    assert summary["second_opinion_ms"] == 325.0
    summary["confidence"] = curve_summary(curve_of(records))
    report = markdown_tables({"c": summary}, THRESHOLDS)
    assert "Second opinions" in report and "c 6, 2, 1 right; 3, 2, 1 right; 325 ms" in report
    alone = summarize(records[6:], THRESHOLDS)
    alone["confidence"] = curve_summary(curve_of(records[6:]))
    assert "Second opinions" not in markdown_tables({"c": alone}, THRESHOLDS)
