"""``slloc models build``: export every requested model, skipping valid existing ones.

Scripts and images name what to build by feature configuration (``--features``), never by model
file: ``models_for_features`` reads the models from the presets table
(``services/features/configs.py``), so a preset with a new exported extractor or matcher is
built by the scripts that build every preset (``all``) or auto's choices (``auto``) as it is.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from functools import partial
from pathlib import Path

from services.features.configs import (
    AUTO,
    AUTO_CHOICES,
    FEATURE_CONFIGS,
    PREFERRED_MODELS,
    feature_config_names,
)
from services.runtime.manifest import ModelEntry, read_manifest, verified_path, write_entry

DEFAULT_MODELS = PREFERRED_MODELS  # the models of the feature configuration auto prefers
ALL_FEATURES = "all"  # in ``--features``: every preset
# the names ``--features`` takes besides the presets: the presets each stands for
FEATURE_SETS: dict[str, tuple[str, ...]] = {
    AUTO: AUTO_CHOICES,  # every preset auto may pick
    ALL_FEATURES: tuple(FEATURE_CONFIGS),
}


def feature_set_names() -> list[str]:
    """Every name ``--features`` takes: the sets, then the presets."""
    return [*FEATURE_SETS, *feature_config_names()]


def models_for_features(names: Iterable[str]) -> tuple[str, ...]:
    """The exported models the feature configurations ``names`` need, in the table's order
    within each and each once (SIFT's none). ``auto`` stands for every preset auto may pick,
    ``all`` for every preset.

    Raises:
        ValueError: a name that is neither a preset nor a set, with the known names.
    """
    models: dict[str, None] = {}
    for name in names:
        presets = FEATURE_SETS.get(name, (name,))
        for preset in presets:
            config = FEATURE_CONFIGS.get(preset)
            if config is None:
                raise ValueError(
                    f"unknown feature configuration {name!r}; known: "
                    f"{', '.join(feature_set_names())}"
                )
            models.update(dict.fromkeys(config.models))
    return tuple(models)


def _exporter(name: str) -> tuple[Callable[[Path], ModelEntry], int]:
    """The export function for ``name`` and the version of the graph it writes."""
    from tools.export.aliked import ALIKED_MODELS, export_aliked
    from tools.export.disk import DISK_MODELS, export_disk
    from tools.export.lightglue import EXPORT_VERSION, MATCHERS, export_lightglue
    from tools.export.xfeat import XFEAT_MODELS, export_xfeat

    if name in ALIKED_MODELS:
        return (lambda models_dir: export_aliked(name, models_dir)), 1
    if name in DISK_MODELS:
        return export_disk, 1
    if name in XFEAT_MODELS:
        return export_xfeat, 1
    for features, source in MATCHERS.items():
        if name == source.name:
            return partial(export_lightglue, features), EXPORT_VERSION
    known = [*ALIKED_MODELS, *DISK_MODELS, *XFEAT_MODELS, *(s.name for s in MATCHERS.values())]
    raise ValueError(f"unknown model {name!r}; known: {', '.join(known)}")


def is_current(models_dir: Path, name: str, version: int) -> bool:
    """Whether ``name`` is in the manifest, its file intact, and exported by exporter
    ``version`` or later (entries without ``export_version`` are version 1)."""
    entry = read_manifest(models_dir).get(name)
    if entry is None or int(entry.config.get("export_version", 1)) < version:
        return False
    try:
        verified_path(models_dir, entry)
    except (OSError, ValueError):
        return False
    return True


def build_models(
    models_dir: Path,
    names: tuple[str, ...] = DEFAULT_MODELS,
    force: bool = False,
    log: Callable[[str], None] = print,
) -> list[ModelEntry]:
    """Export ``names`` into ``models_dir`` and record them in its manifest."""
    exporters = {name: _exporter(name) for name in names}  # unknown names fail before work
    models_dir.mkdir(parents=True, exist_ok=True)
    built = []
    for i, (name, (export, version)) in enumerate(exporters.items(), start=1):
        if not force and is_current(models_dir, name, version):
            log(f"[{i}/{len(names)}] {name}: up to date")
            continue
        log(f"[{i}/{len(names)}] {name}: exporting and checking against PyTorch …")
        start = time.perf_counter()
        entry = export(models_dir)
        write_entry(models_dir, entry)
        built.append(entry)
        elapsed = time.perf_counter() - start
        log(f"[{i}/{len(names)}] {name}: written {entry.file} in {elapsed:.0f} s")
    return built
