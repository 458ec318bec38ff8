"""Forward motion: references along a straight line, the query on that line looking along it
(a driving frame). Rays of a point near the focus of expansion are almost parallel in every
reference, the configuration whose singular linear systems once escaped as exceptions; every
estimator must answer with a pose or a failure reason."""

from __future__ import annotations

from dataclasses import replace

import pytest

from services.estimators.base import FailureReason
from services.estimators.options import EstimatorOptions
from services.estimators.registry import DEPTH_ESTIMATORS, estimator_names, get_estimator
from services.localization.localizer import LocalizeParams, Localizer
from services.references.memory import MemoryReferenceStore
from tools.synthetic.scene import SyntheticScene, SyntheticView, encode_depth_png, encode_png

REFERENCE_DISTANCES = [-5.0 + 0.75 * i for i in range(9)]  # along +z, the way they look
QUERY_DISTANCES = [-3.4, -1.9]  # between references, on their line


@pytest.fixture(scope="module")
def road(localizer: Localizer, scene: SyntheticScene) -> MemoryReferenceStore:
    store = MemoryReferenceStore()
    for view in scene.forward_views(REFERENCE_DISTANCES, prefix="road"):
        data = localizer.describe_reference(
            encode_png(view.image), view.camera, encode_depth_png(view.depth)
        )
        store.add(view.name, view.camera, view.cam_from_world, data)
    return store


@pytest.fixture(scope="module")
def drives(scene: SyntheticScene) -> list[SyntheticView]:
    return scene.forward_views(QUERY_DISTANCES, prefix="drive")


@pytest.mark.parametrize("max_error_px", [2.0])
@pytest.mark.parametrize("name", estimator_names())
def test_every_estimator_answers_on_forward_motion(
    name: str,
    max_error_px: float,
    localizer: Localizer,
    road: MemoryReferenceStore,
    drives: list[SyntheticView],
) -> None:
    options = EstimatorOptions()
    options = replace(options, ransac=replace(options.ransac, max_error_px=max_error_px))
    for view in drives:
        depth = encode_depth_png(view.depth) if name in DEPTH_ESTIMATORS else None
        result = localizer.localize(
            encode_png(view.image),
            LocalizeParams(camera=view.camera, estimator=get_estimator(name), options=options),
            road,
            depth,
        )
        if result.localized:
            assert result.cam_from_world is not None and result.reason is None
        else:
            assert result.reason in set(FailureReason), (name, view.name, result.reason)
