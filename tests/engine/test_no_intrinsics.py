"""Queries without intrinsics through the whole pipeline on rendered images (SIFT features):
the focal length is estimated from the matches or the answer is ``focal_unobservable``; a
confident answer is never a wrong one (issue 12)."""

from __future__ import annotations

import pytest

from services.estimators.registry import get_estimator
from services.geometry.rigid import pose_error
from services.localization.localizer import LocalizeParams, Localizer
from services.references.memory import MemoryReferenceStore
from tools.synthetic.scene import SyntheticScene, SyntheticView, encode_png


@pytest.mark.parametrize("focal", [500.0, 380.0, 700.0])
@pytest.mark.parametrize("estimator", ["e5p1", "local_tri_all"])
def test_queries_without_intrinsics(
    focal: float, estimator: str, localizer: Localizer, store: MemoryReferenceStore
) -> None:
    """Queries rendered with a focal length of 500 px (the references'), a wider and a longer
    one; the default guess would be 768 px. Each answer is the estimated focal within 5 % and a
    pose within 5 cm, or localized: false; a confidence above 0.8 is never 25 cm off."""
    queries = SyntheticScene(seed=0, focal=focal).views(4, stream=2, prefix="query")
    localized = 0
    for view in queries:
        result = localizer.localize(
            encode_png(view.image),
            LocalizeParams(camera=None, estimator=get_estimator(estimator)),
            store,
        )
        assert result.camera_source == "estimated"
        if not result.localized:
            assert result.reason in ("focal_unobservable", "no_consensus", "too_few_matches")
            continue
        assert result.cam_from_world is not None and result.camera is not None
        localized += 1
        assert abs(result.camera.params[0] / focal - 1.0) < 0.05, result.stats
        dt, dr = pose_error(result.cam_from_world, view.cam_from_world)
        assert dt < 0.05 and dr < 1.0, (dt, dr, result.stats)
        assert result.uncertainty is not None and result.uncertainty.position_m > 0
        assert not (result.confidence > 0.8 and dt > 0.25)
    assert localized >= 2


def test_request_camera_is_echoed_with_uncertainty(
    localizer: Localizer, store: MemoryReferenceStore, query_views: list[SyntheticView]
) -> None:
    view = query_views[0]
    result = localizer.localize(encode_png(view.image), LocalizeParams(camera=view.camera), store)
    assert result.localized and result.cam_from_world is not None
    assert result.camera == view.camera and result.camera_source == "request"
    assert result.uncertainty is not None
    dt, dr = pose_error(result.cam_from_world, view.cam_from_world)
    assert dt < 3 * result.uncertainty.position_m + 0.01
    assert dr < 3 * result.uncertainty.rotation_deg + 0.1
    assert result.stats["structure_position_sigma_m"] == result.uncertainty.position_m
    assert result.stats["position_sigma_m"] == result.uncertainty.given_points_position_m
