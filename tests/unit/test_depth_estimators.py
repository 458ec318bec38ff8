"""The registry's depth sets follow the registered estimators' ``needs_depth``: one added with
``register()`` that needs depth is among them, and ``auto``'s plans name registered estimators."""

from __future__ import annotations

import pytest

from services.estimators import registry
from services.estimators.auto import ROLES, check_roles
from services.estimators.base import EstimateResult, FailureReason, ReferenceObservation
from services.estimators.options import EstimatorOptions
from services.geometry.camera import Camera


class _DepthDummy:
    name = "dummy_with_depth"
    needs_depth = True

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult:
        return EstimateResult.failure(FailureReason.NO_CONSENSUS, references)


def test_a_registered_depth_estimator_is_among_the_depth_estimators(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(registry, "_ESTIMATORS", dict(registry._ESTIMATORS))
    assert "dummy_with_depth" not in registry.DEPTH_ESTIMATORS
    registry.register(_DepthDummy())
    assert "dummy_with_depth" in registry.DEPTH_ESTIMATORS
    assert "dummy_with_depth" in registry.DEPTH_USING_ESTIMATORS
    assert sorted(registry.DEPTH_ESTIMATORS) == ["dummy_with_depth", "e3p1", "essential_3pt_depth"]
    assert "auto" in registry.DEPTH_USING_ESTIMATORS and "auto" not in registry.DEPTH_ESTIMATORS


def test_autos_roles_must_be_registered_as_the_plans_assume() -> None:
    candidates = {name: registry.get_estimator(name) for name in ROLES}
    check_roles(candidates)
    with pytest.raises(ValueError, match="not registered"):
        check_roles({k: v for k, v in candidates.items() if k != "motion_averaging"})
    with pytest.raises(ValueError, match="depth"):
        check_roles({**candidates, "e3p1": candidates["e5p1"]})
