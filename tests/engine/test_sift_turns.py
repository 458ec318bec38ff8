"""What an image of nothing in the map costs with SIFT (a real map of rendered views, real
SIFT). SIFT is rotation invariant: a sideways query localizes at the turn it was uploaded at,
and no other quarter turn is searched, for it or for an image of nothing in the map (which paid
three more extractions and matchings). A pose search that draws every hypothesis it may
without a pose ends the localization: no fallback estimator, no wider spread of references."""

from __future__ import annotations

import numpy as np
import pytest

from services.estimators.ransac import searched_in_vain
from services.geometry.intrinsics_adaptation import rotate_camera, rotated_from_camera
from services.geometry.rigid import Rigid3d, pose_error
from services.localization.localizer import LocalizeParams, Localizer
from services.references.memory import MemoryReferenceStore
from tools.synthetic.scene import SyntheticView, encode_png, unrelated_image


@pytest.mark.parametrize("turn", [90, 180, 270])
def test_a_sideways_query_localizes_as_uploaded(
    turn: int, localizer: Localizer, store: MemoryReferenceStore, query_views: list[SyntheticView]
) -> None:
    assert localizer.extractor.rotation_invariant
    query = query_views[0]
    R = rotated_from_camera(turn)
    truth = Rigid3d(R @ query.cam_from_world.rotation, R @ query.cam_from_world.translation)
    image = np.ascontiguousarray(np.rot90(query.image, k=-(turn // 90)))
    params = LocalizeParams(camera=rotate_camera(query.camera, turn))
    result = localizer.localize(encode_png(image), params, store)
    assert result.localized and result.cam_from_world is not None, result.reason
    dt, dr = pose_error(result.cam_from_world, truth)
    assert dt < 0.01 and dr < 0.2, (dt, dr, result.confidence)
    assert result.upright_turn_deg == 0
    assert result.stats["orientation_attempts"] == 1


def test_an_image_of_nothing_is_extracted_once(
    localizer: Localizer, store: MemoryReferenceStore, query_views: list[SyntheticView]
) -> None:
    params = LocalizeParams(camera=query_views[0].camera)
    result = localizer.localize(encode_png(unrelated_image(0)), params, store)
    assert not result.localized, result.confidence
    assert result.stats.get("orientation_attempts", 1) == 1, result.stats


def test_an_image_of_nothing_ends_with_its_pose_search(
    localizer: Localizer, store: MemoryReferenceStore, query_views: list[SyntheticView]
) -> None:
    """``auto``'s first estimator (``e5p1``, run with ``local_tri_all``) draws every
    hypothesis it may without a pose: no fallback estimator and no wider spread of references
    is tried on top."""
    params = LocalizeParams(camera=query_views[0].camera)
    for seed in range(3):
        result = localizer.localize(encode_png(unrelated_image(seed)), params, store)
        assert not result.localized, result.confidence
        assert searched_in_vain(result.stats, params.options.ransac), result.stats
        assert result.stats["auto_attempts"] == 2, result.stats  # e5p1 and local_tri_all
        assert result.stats.get("wider_retrieval", 0.0) == 0.0, result.stats
