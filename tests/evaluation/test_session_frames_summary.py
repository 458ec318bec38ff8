"""``python -m tools.benchmarks.session_frames``: the figures of several-frame answers, on
hand-made answers."""

from __future__ import annotations

import math
from typing import Any

import pytest

from tools.benchmarks.session_frames import summarize


def _answer(
    error_m: float,
    error_deg: float,
    confidence: float,
    reason: str | None = None,
    sigma: tuple[float, float] | None = None,
) -> Any:
    return {
        "query": "q",
        "localized": reason is None,
        "reason": reason,
        "confidence": confidence,
        "error_m": error_m if reason is None else math.inf,
        "error_deg": error_deg if reason is None else math.inf,
        "ms": 100.0,
        "stats": {}
        if sigma is None
        else {"structure_position_sigma_m": sigma[0], "structure_rotation_sigma_deg": sigma[1]},
    }


def test_the_summary_counts_right_confident_wrong_and_far_answers() -> None:
    answers = [
        _answer(0.01, 0.2, 0.95, sigma=(0.01, 0.1)),  # right, confident, within 3σ
        _answer(0.10, 1.0, 0.60, sigma=(0.05, 0.2)),  # within (25 cm, 2°) only; rotation > 3σ
        _answer(1.50, 37.0, 0.95),  # confidently wrong, more than 1 m off, no uncertainty
        _answer(0.40, 0.3, 0.50),  # wrong, not confident
        _answer(0.0, 0.0, 0.0, "inconsistent_frames"),
    ]
    summary = summarize(answers)
    assert summary["queries"] == 5 and summary["localized"] == 4
    assert summary["recall"]["5cm_5deg"] == pytest.approx(0.2)
    assert summary["recall"]["25cm_2deg"] == pytest.approx(0.4)
    assert summary["confident"] == 2 and summary["confident_wrong"] == 1
    assert summary["far"] == 1
    assert summary["with_uncertainty"] == 2 and summary["within_3_uncertainty"] == 1
    assert summary["failures"] == {"inconsistent_frames": 1}
    assert summary["median_error_m"] == pytest.approx(0.40)
