"""``slloc eval`` scores the poses a ``min_confidence`` withholds: a ``low_confidence`` answer's
candidate is compared with the ground truth, and the summary counts the right answers the
threshold turned away. The real engine on a rendered scene with exact poses, and hand-made
records."""

from __future__ import annotations

import math
from collections.abc import Iterator

import pytest

from app.settings import get_settings
from tests.evaluation.records import hand_made
from tools.evaluation.confidence_curve import curve_of, curve_summary
from tools.evaluation.evaluate import localize_params
from tools.evaluation.metrics import QueryRecord, ReferencePoses, make_record, summarize
from tools.evaluation.report import markdown_tables
from tools.evaluation.runner import InProcessRunner
from tools.evaluation.split import Split

THRESHOLDS = ((0.05, 5.0), (0.25, 2.0))


@pytest.fixture(scope="module")
def runner(split: Split) -> Iterator[InProcessRunner]:
    running = InProcessRunner("sift", get_settings().models_dir)
    for image in split.references:
        running.add_reference(image, None)
    running.index_references(len(split.references))
    yield running
    running.close()


def test_a_withheld_pose_is_scored_as_the_answer_would_be(
    split: Split, runner: InProcessRunner
) -> None:
    references = ReferencePoses.of({r.name: r.cam_from_world for r in split.references})
    query = split.queries[0]
    image = query.image_path.read_bytes()
    params = localize_params(query.camera, "auto", top_k=10)
    answered = make_record(
        "sift/auto",
        query.name,
        runner.localize(image, None, params),
        query.cam_from_world,
        references,
    )
    withheld = make_record(
        "sift/auto",
        query.name,
        runner.localize(image, None, {**params, "min_confidence": 1.0}),
        query.cam_from_world,
        references,
    )
    assert answered.localized and answered.position_error_m < 0.05
    assert math.isinf(answered.candidate_position_error_m)  # an answer has no candidate
    assert not withheld.localized and withheld.reason == "low_confidence"
    assert math.isinf(withheld.position_error_m)  # a failure for the recall
    assert withheld.candidate_position_error_m == pytest.approx(answered.position_error_m)
    assert withheld.candidate_rotation_error_deg == pytest.approx(answered.rotation_error_deg)
    summary = summarize([withheld], THRESHOLDS)
    assert summary["withheld"] == 1 and summary["withheld_right"] == 1
    assert summary["recall"]["25cm_2deg"] == 0.0


def test_the_summary_counts_the_right_answers_withheld() -> None:
    def withheld(pos: float, rot: float) -> QueryRecord:
        return hand_made(
            reason="low_confidence",
            candidate_position_error_m=pos,
            candidate_rotation_error_deg=rot,
        )

    records = [
        withheld(0.10, 1.0),  # right
        withheld(0.30, 1.0),  # more than 25 cm off
        withheld(0.10, 6.0),  # more than 5° off
        withheld(math.inf, math.inf),  # no candidate
        hand_made(),  # a failure of another reason
        hand_made(pos=0.01, rot=0.1, confidence=0.9),  # an answer
    ]
    summary = summarize(records, THRESHOLDS)
    assert (summary["withheld"], summary["withheld_right"]) == (4, 1)
    summary["confidence"] = curve_summary(curve_of(records))
    report = markdown_tables({"c": summary}, THRESHOLDS)
    assert "Answers withheld below `min_confidence`" in report
    assert "c 4 / 1 right" in report
