"""The markdown table of the feature configurations (``slloc features`` prints it;
docs/models.md holds it verbatim), written from ``services/features/configs.py``."""

from __future__ import annotations

from services.features.configs import (
    AUTO_CHOICES,
    FALLBACK_FEATURES,
    FEATURE_CONFIGS,
    PREFERRED_FEATURES,
    SIFT,
    FeatureConfig,
)

_ROLES = {
    PREFERRED_FEATURES: "auto's choice",
    AUTO_CHOICES[1]: "auto's second choice",
    FALLBACK_FEATURES: "auto's fallback",
}


def _features(config: FeatureConfig) -> str:
    extractor = "OpenCV SIFT (RootSIFT)" if config.extractor == SIFT else f"`{config.extractor}`"
    return f"{extractor}, {config.max_keypoints} keypoints, longer side {config.max_side} px"


def _matching(config: FeatureConfig) -> str:
    floor = "" if config.min_similarity is None else f", cosine > {config.min_similarity:g}"
    nearest = f"mutual nearest neighbours (ratio {config.ratio:g}{floor})"
    if config.lightglue is None:
        return nearest
    lightglue = f"`{config.lightglue}`"
    keypoints = (
        "all keypoints"
        if config.lightglue_keypoints is None
        else f"each image's {config.lightglue_keypoints} best keypoints"
    )
    if config.lightglue_pairs is None:
        return f"{lightglue} on every retrieved pair, {keypoints}"
    pairs = "pair" if config.lightglue_pairs == 1 else f"{config.lightglue_pairs} pairs"
    return (
        f"{nearest} on every retrieved pair, then {lightglue} on the {pairs} with the most "
        f"of them, {keypoints}"
    )


def feature_table() -> str:
    """One row per preset: name, features, matching, the models it needs and when to use it."""
    lines = [
        "| `SLLOC_FEATURES` | features | matching | models needed | use |",
        "|---|---|---|---|---|",
    ]
    for config in FEATURE_CONFIGS.values():
        role = f" ({_ROLES[config.name]})" if config.name in _ROLES else ""
        models = ", ".join(f"`{m}`" for m in config.models) or "none"
        lines.append(
            f"| `{config.name}`{role} | {_features(config)} | {_matching(config)} | {models} "
            f"| {config.description} |"
        )
    return "\n".join(lines) + "\n"
