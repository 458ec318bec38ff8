"""Adding an estimator takes one file and its registration: a dummy, registered before the app
is imported, is in the API's estimator enum, in the generated OpenAPI document and among the
contract tests, with no other file touched."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

from services.estimators.base import EstimateResult, FailureReason, ReferenceObservation
from services.estimators.options import EstimatorOptions
from services.estimators.registry import register
from services.geometry.camera import Camera

ROOT = Path(__file__).resolve().parents[2]
DUMMY = "dummy_for_the_registry_test"


# --- the new estimator's file ---
class DummyEstimator:
    """Answers no pose."""

    name = DUMMY
    needs_depth = False

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult:
        return EstimateResult.failure(FailureReason.NO_CONSENSUS, references)


# --- its registration ---
def register_dummy() -> None:
    register(DummyEstimator())


# run in a fresh interpreter: the registry of this test session stays as it is
PROBE = textwrap.dedent(
    """
    import contextlib, io, json, sys

    import pytest

    from tests.estimators.test_new_estimator import DUMMY, register_dummy

    register_dummy()
    from app.openapi import openapi_document
    from app.schemas.estimators import EstimatorEnum

    document = json.loads(openapi_document())
    collected = io.StringIO()
    with contextlib.redirect_stdout(collected):
        pytest.main(["--collect-only", "-q", "-p", "no:cacheprovider",
                     "tests/estimators/test_contract.py"])
    print(json.dumps({
        "enum": [member.value for member in EstimatorEnum],
        "openapi": document["components"]["schemas"]["EstimatorName"]["enum"],
        "contract": [line for line in collected.getvalue().splitlines() if DUMMY in line],
    }))
    """
)


def test_a_registered_estimator_reaches_the_api_and_the_contract_tests() -> None:
    done = subprocess.run(
        [sys.executable, "-c", PROBE], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.splitlines()[-1])
    assert DUMMY in seen["enum"]
    assert DUMMY in seen["openapi"]
    for contract in ("test_recovers_ground_truth", "test_no_references", "test_only_outliers"):
        assert f"tests/estimators/test_contract.py::{contract}[{DUMMY}]" in seen["contract"]
