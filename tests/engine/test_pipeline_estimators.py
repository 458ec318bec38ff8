"""Every registered estimator through the whole pipeline on rendered images (decode → SIFT →
retrieval → matching → estimate), with exact ground truth from the synthetic scene."""

from __future__ import annotations

import numpy as np
import pytest

from services.estimators.registry import DEPTH_ESTIMATORS, estimator_names, get_estimator
from services.geometry.rigid import pose_error
from services.localization.localizer import LocalizeParams, Localizer
from services.references.memory import MemoryReferenceStore
from tools.synthetic.scene import (
    SyntheticScene,
    SyntheticView,
    encode_depth_png,
    encode_png,
    unrelated_image,
)


@pytest.fixture(scope="module")
def store(localizer: Localizer, reference_views: list[SyntheticView]) -> MemoryReferenceStore:
    memory = MemoryReferenceStore()
    for view in reference_views:
        data = localizer.describe_reference(
            encode_png(view.image), view.camera, encode_depth_png(view.depth)
        )
        memory.add(view.name, view.camera, view.cam_from_world, data)
    return memory


@pytest.mark.parametrize("name", estimator_names())
def test_estimator_on_rendered_queries(
    name: str,
    localizer: Localizer,
    store: MemoryReferenceStore,
    scene: SyntheticScene,
    query_views: list[SyntheticView],
) -> None:
    queries = query_views[:4]
    errors = []
    for view in queries:
        depth = encode_depth_png(view.depth) if name in DEPTH_ESTIMATORS else None
        result = localizer.localize(
            encode_png(view.image),
            LocalizeParams(camera=view.camera, estimator=get_estimator(name)),
            store,
            depth,
        )
        assert result.localized, (name, view.name, result.reason)
        assert result.cam_from_world is not None
        errors.append(pose_error(result.cam_from_world, view.cam_from_world))
    if name == "pose_approx":
        return  # the baseline: a pose, but no accuracy promise
    for dt, dr in errors:
        assert dt < 0.01 * scene.extent and dr < 0.5, (name, errors)


@pytest.mark.parametrize("name", [n for n in estimator_names() if n != "pose_approx"])
def test_estimator_rejects_unrelated_image(
    name: str, localizer: Localizer, store: MemoryReferenceStore, scene: SyntheticScene
) -> None:
    image = unrelated_image(7)
    depth = encode_depth_png(np.full(image.shape[:2], 3.0, np.float32))
    result = localizer.localize(
        encode_png(image),
        LocalizeParams(camera=scene.camera, estimator=get_estimator(name)),
        store,
        depth if name in DEPTH_ESTIMATORS else None,
    )
    assert not result.localized and result.cam_from_world is None
    assert result.reason in ("no_consensus", "too_few_matches", "degenerate_geometry")


def test_pose_below_min_confidence_is_a_candidate(
    localizer: Localizer, store: MemoryReferenceStore, query_views: list[SyntheticView]
) -> None:
    """A verified pose less confident than the request's floor is answered low_confidence,
    not localized, with the same pose as its candidate; a floor it meets changes nothing."""
    view = query_views[0]
    image = encode_png(view.image)
    answered = localizer.localize(image, LocalizeParams(camera=view.camera), store)
    assert answered.localized and answered.cam_from_world is not None
    assert 0.0 < answered.confidence < 1.0
    met = localizer.localize(
        image, LocalizeParams(camera=view.camera, min_confidence=answered.confidence), store
    )
    assert met.localized and met.candidate is None
    floor = (answered.confidence + 1.0) / 2.0
    refused = localizer.localize(
        image, LocalizeParams(camera=view.camera, min_confidence=floor), store
    )
    assert not refused.localized and refused.reason == "low_confidence"
    assert refused.cam_from_world is None and refused.uncertainty is None
    assert refused.candidate is not None
    np.testing.assert_allclose(refused.candidate.matrix, answered.cam_from_world.matrix, atol=1e-9)
    assert refused.confidence == answered.confidence
