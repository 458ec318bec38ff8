"""The named feature configurations (presets): a local-feature extractor with its budget and
the matcher for its features, one row each.

``SLLOC_FEATURES`` and ``slloc eval --features`` take these names; the settings help, the
docs' table (Models and presets; ``slloc features`` prints it) and the feature benchmark read
this table, and ``services/components.py`` builds an (extractor, matcher) pair from a row.
"""

from __future__ import annotations

from dataclasses import dataclass

from services.errors import UnknownComponentError

AUTO = "auto"  # the first of AUTO_CHOICES whose models are built, else the fallback
SIFT = "sift"  # the extractor that needs no exported model
DISK_KEYPOINTS = 1024
# XFeat's budget with nearest neighbours alone (``xfeat``): on redkitchen 2048 keypoints localize
# more queries than 1024 (56 / 78 / 52 % against 52 / 76 / 46 %, e5p1); ``xfeat-lg`` keeps 1024
# and lets LighterGlue match its two best pairs
XFEAT_KEYPOINTS = 2048
# XFeat's own matcher's floor on the cosine similarity: with 2048 keypoints and the ratio test
# alone, images of another scene kept ~1700 matches a query and some localized
XFEAT_MIN_SIMILARITY = 0.82
# SIFT's budget: a 640 × 480 indoor frame seldom reaches 2048 keypoints, an outdoor frame
# does. On kitti05 4096 take the median error from 0.6 to 0.5 cm and the p90 from 1.3 to
# 1.1 cm, for about 100 ms more matching a query; redkitchen answers as with 2048
SIFT_KEYPOINTS = 4096


@dataclass(frozen=True)
class FeatureConfig:
    """name: what ``SLLOC_FEATURES`` takes. extractor: ``"sift"`` or an exported keypoint
    model. max_keypoints / max_side: keypoints per image and the longer image side (px) it is
    resized to before detection. lightglue: the exported LightGlue model for the extractor's
    features, or None for mutual nearest neighbours alone. lightglue_pairs: LightGlue runs on
    the retrieved pairs with the most nearest-neighbour matches, this many (None: every pair;
    the others keep their nearest-neighbour matches). lightglue_keypoints: each image's best
    keypoints LightGlue sees (None: all). ratio: the nearest neighbours' ratio test (LightGlue's
    first pass included). min_similarity: the nearest neighbours' least cosine similarity (None:
    no floor). refine_matches: each match's reference keypoint is refined to sub-pixel on
    the two images (``services.matching.refinement``), for extractors whose keypoints sit on
    the pixel grid of a shrunken image. description: one line on when to choose it.
    """

    name: str
    extractor: str
    description: str
    max_keypoints: int = 1024
    max_side: int = 640
    lightglue: str | None = None
    lightglue_pairs: int | None = None
    lightglue_keypoints: int | None = None
    ratio: float = 0.95
    min_similarity: float | None = None
    refine_matches: bool = False

    def __post_init__(self) -> None:
        if self.lightglue is None and (
            self.lightglue_pairs is not None or self.lightglue_keypoints is not None
        ):
            raise ValueError(f"{self.name}: lightglue_pairs / lightglue_keypoints need lightglue")
        if self.lightglue_pairs is not None and self.lightglue_pairs < 1:
            raise ValueError(f"{self.name}: lightglue_pairs must be >= 1 or None")

    @property
    def models(self) -> tuple[str, ...]:
        """The exported models it needs (none for SIFT)."""
        return tuple(m for m in (self.extractor, self.lightglue) if m is not None and m != SIFT)


FEATURE_CONFIGS: dict[str, FeatureConfig] = {
    config.name: config
    for config in (
        FeatureConfig(
            "aliked",
            "aliked-n16",
            "more accurate than xfeat-lg on some scenes, ~1.4 s a query on two cores",
            lightglue="lightglue-aliked",
            lightglue_pairs=3,
            lightglue_keypoints=512,
        ),
        FeatureConfig(
            "aliked-fast",
            "aliked-n16",
            "LightGlue in about half aliked's time a query",
            max_side=480,
            lightglue="lightglue-aliked",
            lightglue_pairs=1,
            lightglue_keypoints=256,
        ),
        FeatureConfig(
            "aliked-full",
            "aliked-n16",
            "the most LightGlue matches, slowest: ~0.7 s a pair",
            lightglue="lightglue-aliked",
        ),
        FeatureConfig("aliked-nn", "aliked-n16", "ALIKED without LightGlue"),
        FeatureConfig(
            "disk",
            "disk",
            "more correct matches a pair than ALIKED, twice its extraction time",
            max_keypoints=DISK_KEYPOINTS,
            lightglue="lightglue-disk",
            lightglue_pairs=3,
        ),
        FeatureConfig("disk-fast", "disk", "DISK without LightGlue", max_keypoints=DISK_KEYPOINTS),
        FeatureConfig(
            "xfeat",
            "xfeat",
            "XFeat without LighterGlue: as fast as sift, below its accuracy on redkitchen",
            max_keypoints=XFEAT_KEYPOINTS,
            min_similarity=XFEAT_MIN_SIMILARITY,
            refine_matches=True,
        ),
        FeatureConfig(
            "xfeat-lg",
            "xfeat",
            "the real-time default: ~0.2 s a query on two cores, about aliked's accuracy",
            lightglue="lighterglue-xfeat",
            lightglue_pairs=2,
            lightglue_keypoints=512,
            refine_matches=True,
        ),
        FeatureConfig(
            "xfeat-full",
            "xfeat",
            "XFeat with LighterGlue on every pair: ~0.6 s a query",
            lightglue="lighterglue-xfeat",
            lightglue_keypoints=512,
            refine_matches=True,
        ),
        FeatureConfig(
            SIFT, SIFT, "needs no weights", max_keypoints=SIFT_KEYPOINTS, max_side=1024, ratio=0.8
        ),
    )
}

# what AUTO picks, in order: the first whose models are built; a database whose references
# were described by one of them keeps it (``services/components.resolve_features``)
AUTO_CHOICES = ("xfeat-lg", "aliked")
PREFERRED_FEATURES = AUTO_CHOICES[0]
PREFERRED_MODELS = FEATURE_CONFIGS[PREFERRED_FEATURES].models
FALLBACK_FEATURES = SIFT  # what AUTO picks otherwise: needs no weights


def described_by(config: FeatureConfig, feature_model: str) -> bool:
    """Whether a reference stored as described by ``feature_model`` (its extractor's name,
    e.g. ``xfeat-1024-640``) holds the features of ``config``'s extractor."""
    return feature_model.startswith(f"{config.extractor}-")


def feature_config_names() -> list[str]:
    return sorted(FEATURE_CONFIGS)


def get_feature_config(name: str) -> FeatureConfig:
    """The preset called ``name``.

    Raises:
        UnknownComponentError: no preset (nor ``auto``) is called ``name``.
    """
    try:
        return FEATURE_CONFIGS[name]
    except KeyError:
        raise UnknownComponentError(
            f"unknown feature configuration {name!r}; known: "
            f"{', '.join([AUTO, *feature_config_names()])}"
        ) from None
