"""The wider retrieval of an unsure query (``Localizer.match_wider``) on the README demo's map
with the default XFeat + LighterGlue: the references both retrievals share keep their matches
(matched once), the new ones are matched, and a map no larger than ``top_k`` is not matched
again."""

from __future__ import annotations

import pytest

from services.components import EngineConfig, build_localizer
from services.localization.clock import StageClock
from services.localization.localizer import LocalizeParams, Localizer
from services.localization.stages import MatchedQuery
from services.references.memory import MemoryReferenceStore
from tests.models.conftest import MODELS_DIR
from tools.synthetic.scene import SyntheticView, encode_png


@pytest.fixture(scope="module")
def xfeat_lg(xfeat_models: object) -> Localizer:
    return build_localizer(EngineConfig.resolve(MODELS_DIR, 40_000_000, "xfeat-lg"))


@pytest.fixture(scope="module")
def demo_map(xfeat_lg: Localizer, reference_views: list[SyntheticView]) -> MemoryReferenceStore:
    store = MemoryReferenceStore()
    for view in reference_views:
        data = xfeat_lg.describe_reference(encode_png(view.image), view.camera)
        store.add(view.name, view.camera, view.cam_from_world, data)
    return store


def _matched_twice(
    localizer: Localizer, store: MemoryReferenceStore, query: SyntheticView, top_k: int
) -> tuple[MatchedQuery, MatchedQuery | None]:
    params = LocalizeParams(camera=query.camera, top_k=top_k)
    clock = StageClock(None)
    decoded = localizer.decode(encode_png(query.image), params, None)
    first = localizer.match(decoded, 0, params, store, clock, None)
    return first, localizer.match_wider(decoded, first, params, store, clock, None)


def test_the_wider_match_keeps_the_shared_matches(
    xfeat_lg: Localizer, demo_map: MemoryReferenceStore, query_views: list[SyntheticView]
) -> None:
    first, wider = _matched_twice(xfeat_lg, demo_map, query_views[0], top_k=4)
    assert wider is not None
    shared = {o.image_id: o for o in first.observations}
    ids = [o.image_id for o in wider.observations]
    assert len(ids) == 4 and set(ids) != set(shared)
    for observation in wider.observations:
        if observation.image_id in shared:
            assert observation is shared[observation.image_id]  # matched once
        else:
            assert len(observation.query_xy) > 0
        assert observation.image_id in wider.names


def test_a_map_no_larger_than_top_k_is_not_matched_again(
    xfeat_lg: Localizer, demo_map: MemoryReferenceStore, query_views: list[SyntheticView]
) -> None:
    size = len(demo_map.retrieval_index().image_ids)
    _, wider = _matched_twice(xfeat_lg, demo_map, query_views[0], top_k=size)
    assert wider is None
