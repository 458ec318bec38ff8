"""The large problems the time budget is held on (``tests/engine/test_time_budget.py`` and
``tools.benchmarks.time_budget``): 100 references of 1000 matches for the estimators, and a
map of the rendered reference views under several names each for the localizer's stages."""

from __future__ import annotations

from services.confidence.model import default_confidence_model
from services.estimators.base import EstimateResult
from services.estimators.options import EstimatorOptions
from services.estimators.ransac import Deadline
from services.estimators.registry import get_estimator
from services.localization.estimate import answer_pose
from services.localization.localizer import Localizer
from services.references.memory import MemoryReferenceStore
from tools.synthetic.correspondences import SyntheticCorrespondences, make_correspondences
from tools.synthetic.scene import SyntheticView, encode_png

# the localizer's stages: 24 described views under four names each (96 references)
COPIES = 4
TOP_K = 50


def large_correspondences() -> SyntheticCorrespondences:
    """100 references of 1000 matches (30 % outliers) with depth."""
    return make_correspondences(
        seed=5, num_references=100, matches_per_reference=1000, with_depth=True
    )


def answer_in_budget(
    name: str, scene: SyntheticCorrespondences, focal_estimated: bool, budget_s: float
) -> EstimateResult:
    """``name``'s answer on ``scene`` (its camera estimated first when ``focal_estimated``)
    under a time budget of ``budget_s`` seconds."""
    return answer_pose(
        get_estimator(name),
        scene.query_camera,
        focal_estimated,
        scene.references,
        EstimatorOptions(time_budget_s=budget_s),
        Deadline(budget_s),
        default_confidence_model(),
    ).result


def copied_store(
    localizer: Localizer, views: list[SyntheticView], copies: int = COPIES
) -> MemoryReferenceStore:
    """A map of ``views``, each described once and stored under ``copies`` names."""
    store = MemoryReferenceStore()
    for view in views:
        data = localizer.describe_reference(encode_png(view.image), view.camera)
        for copy in range(copies):
            store.add(f"{view.name}-{copy}", view.camera, view.cam_from_world, data)
    return store
