"""A self-evaluation's votes on the references that cover each held-out one: real SIFT on
rendered views of a synthetic room, one reference's image swapped for another room's."""

from __future__ import annotations

from typing import Any

from services.capture.freshness import Vote, stale_references
from services.estimators.registry import get_estimator
from services.localization.localizer import Localizer
from services.self_evaluation.run import HeldOutPlan, MapReference, evaluate
from tests.conftest import seen_elsewhere
from tools.synthetic.scene import SyntheticView, encode_png

REFERENCES = 12


class _Originals:
    def __init__(self, views: dict[str, SyntheticView]) -> None:
        self.views = views

    def image(self, image_id: str) -> bytes:
        return encode_png(self.views[image_id].image)

    def depth(self, image_id: str) -> bytes | None:
        return None


class _CountingMatcher:
    """The real matcher, counting its pair-by-pair calls (the localization matches with
    ``match_many``, the votes with ``match``)."""

    def __init__(self, matcher: Any) -> None:
        self.matcher = matcher
        self.pairs = 0

    def match(self, *args: Any, **kwargs: Any) -> Any:
        self.pairs += 1
        return self.matcher.match(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.matcher, name)


def test_votes_reuse_the_localization_and_match_only_to_confirm_a_stale_one(
    localizer: Localizer, reference_views: list[SyntheticView]
) -> None:
    views = {f"id{i}": v for i, v in enumerate(reference_views[:REFERENCES])}
    views["id5"] = seen_elsewhere(views["id5"])
    references = [MapReference(i, v.name, v.camera, v.cam_from_world) for i, v in views.items()]
    matcher = _CountingMatcher(localizer.matcher)
    counting = Localizer(
        localizer.extractor,
        matcher,
        localizer.global_descriptor,
        localizer.max_pixels,
    )
    plan = HeldOutPlan(
        local_map=40, radius_m=0.0, top_k=10, estimator=get_estimator("auto"), time_budget_s=None
    )
    votes: list[Vote] = []
    evaluate(counting, references, range(REFERENCES), _Originals(views), plan, 60, votes=votes)
    verdict = stale_references(votes)
    assert [i for i, theirs in verdict.items() if theirs] == ["id5"]
    assert len(verdict) > 6  # most references had a fresh vote
    # the covering references the localizations retrieved voted fresh from their inliers; a
    # stale vote was matched again to count every match (36 votes, 5 pairs matched here)
    stale = len(verdict["id5"])
    assert stale <= matcher.pairs < stale + len(votes) // 4
