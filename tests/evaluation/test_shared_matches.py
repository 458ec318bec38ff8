"""``slloc eval`` describes and matches each query once for all its estimators: the answers
must be those of one localize per estimator, and the map's feature options must reach the map."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from app.settings import get_settings
from app.usecases.maps import require_map
from services.estimators.registry import DEPTH_ESTIMATORS, estimator_names
from tools.evaluation.evaluate import localize_params
from tools.evaluation.runner import InProcessRunner
from tools.evaluation.split import Split


@pytest.fixture(scope="module")
def runner(split: Split) -> Iterator[InProcessRunner]:
    running = InProcessRunner("sift", get_settings().models_dir)
    for image in split.references:
        assert image.depth_path is not None
        running.add_reference(image, image.depth_path.read_bytes())
    running.index_references(len(split.references))
    yield running
    running.close()


def test_every_estimator_answers_as_when_run_alone(split: Split, runner: InProcessRunner) -> None:
    names = estimator_names()
    for query in split.queries[:2]:
        assert query.depth_path is not None
        image, depth = query.image_path.read_bytes(), query.depth_path.read_bytes()
        params = localize_params(query.camera, names[0], top_k=10)
        shared = runner.localize_each(image, depth, params, names)
        assert len(shared) == len(names)
        # one description and matching: the shared stages took the same time for everyone
        assert len({o.timings_ms["match"] for o in shared}) == 1
        # each its own estimation time: the client time of each holds its own, none negative
        for outcome in shared:
            assert outcome.timings_ms["client"] >= outcome.timings_ms["estimate"] > 0
        for name, outcome in zip(names, shared, strict=True):
            alone = runner.localize(
                image, depth if name in DEPTH_ESTIMATORS else None, {**params, "estimator": name}
            )
            key = (query.name, name)
            assert outcome.localized == alone.localized, key
            assert outcome.reason == alone.reason, key
            assert outcome.num_inliers == alone.num_inliers, key
            assert outcome.retrieved == alone.retrieved, key
            assert outcome.confidence == pytest.approx(alone.confidence, abs=1e-12), key
            assert outcome.stats.keys() == alone.stats.keys(), key
            if alone.cam_from_world is None:
                assert outcome.cam_from_world is None, key
                continue
            assert outcome.cam_from_world is not None
            for part in ("rotation", "translation"):
                np.testing.assert_allclose(
                    getattr(outcome.cam_from_world, part),
                    getattr(alone.cam_from_world, part),
                    rtol=0,
                    atol=1e-12,
                    err_msg=str(key),
                )
    localized = [o for o in shared if o.localized]
    assert len(localized) >= len(names) - 1  # the scene is easy: (nearly) every one answers


def test_a_depth_estimator_without_depth_is_its_failure(
    split: Split, runner: InProcessRunner
) -> None:
    query = split.queries[0]
    params = localize_params(query.camera, "e5p1", top_k=10)
    outcomes = runner.localize_each(query.image_path.read_bytes(), None, params, ["e3p1", "e5p1"])
    assert [o.reason for o in outcomes] == ["missing_depth", None]


def test_map_feature_options_reach_the_map() -> None:
    running = InProcessRunner("sift", get_settings().models_dir, max_keypoints=300, max_side=320)
    try:
        with running.sessions() as session:
            row = require_map(session, running.map_id)
            assert (row.max_keypoints, row.max_side) == (300, 320)
    finally:
        running.close()
