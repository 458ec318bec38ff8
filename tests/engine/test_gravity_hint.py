"""A gravity reading that contradicts the pose: a phone held upright whose ``gravity.down``
points up in the camera frame once came back localized, metres off, at confidence 0.000. The
pose is now checked against the reading: a pose that disagrees by more than
``max_angle_deg`` is no answer (``gravity_mismatch``); the right reading localizes."""

from __future__ import annotations

import pytest

from services.geometry.gravity import references_down
from services.geometry.rigid import pose_error
from services.localization.localizer import LocalizeParams, Localizer
from services.localization.query_frame import GravityHint, QueryFrameHints
from services.references.memory import MemoryReferenceStore
from tools.synthetic.scene import SyntheticView, encode_png


@pytest.mark.parametrize("sign", [1.0, -1.0], ids=["upright", "upside-down"])
def test_gravity_reading_against_the_pose(
    sign: float,
    localizer: Localizer,
    store: MemoryReferenceStore,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    view = query_views[0]
    world_down = references_down([ref.cam_from_world for ref in reference_views])
    down = sign * (view.cam_from_world.rotation @ world_down)
    params = LocalizeParams(
        camera=view.camera, frame=QueryFrameHints(gravity=GravityHint(down=down))
    )
    result = localizer.localize(encode_png(view.image), params, store)
    if sign > 0:
        assert result.localized and result.cam_from_world is not None, result.reason
        dt, dr = pose_error(result.cam_from_world, view.cam_from_world)
        assert dt < 0.05 and dr < 1.0
    else:
        assert not result.localized and result.cam_from_world is None
        assert result.reason == "gravity_mismatch", result.reason
