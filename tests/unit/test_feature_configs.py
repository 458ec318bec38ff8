"""The table of feature configurations: what each preset builds, and the texts read from it
(settings help, ``slloc features``, the table on the docs' models page)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from app.settings import Settings
from services.components import (
    EngineConfig,
    ModelsMissingError,
    ModelStore,
    build_features,
    build_localizer,
)
from services.errors import UnknownComponentError
from services.features.configs import (
    AUTO,
    AUTO_CHOICES,
    FEATURE_CONFIGS,
    PREFERRED_FEATURES,
    PREFERRED_MODELS,
    FeatureConfig,
    feature_config_names,
    get_feature_config,
)
from services.runtime.manifest import ModelEntry
from tools import cli
from tools.cli import main
from tools.export import build
from tools.export.build import models_for_features
from tools.feature_table import feature_table

MODELS_PAGE = Path(__file__).resolve().parents[2] / "docs" / "models.md"

# preset → (extractor name, matcher name): the components each preset has always built
BUILDS = {
    "aliked": ("aliked-n16-1024-640", "lightglue-aliked-512kp-top3+mnn-ratio-0.95"),
    "aliked-fast": ("aliked-n16-1024-480", "lightglue-aliked-256kp-top1+mnn-ratio-0.95"),
    "aliked-full": ("aliked-n16-1024-640", "lightglue-aliked-all+mnn-ratio-0.95"),
    "aliked-nn": ("aliked-n16-1024-640", "mnn-ratio-0.95"),
    "disk": ("disk-1024-640", "lightglue-disk-top3+mnn-ratio-0.95"),
    "disk-fast": ("disk-1024-640", "mnn-ratio-0.95"),
    "sift": ("sift-rootsift-4096-1024-c0.02", "mnn-ratio-0.8"),
    "xfeat": ("xfeat-2048-640", "mnn-ratio-0.95-cos-0.82"),
    "xfeat-lg": ("xfeat-1024-640", "lighterglue-xfeat-512kp-top2+mnn-ratio-0.95"),
    "xfeat-full": ("xfeat-1024-640", "lighterglue-xfeat-512kp-all+mnn-ratio-0.95"),
}


class _SessionlessStore(ModelStore):
    """Every model 'built' with a 2048-keypoint budget; records the models asked for."""

    def __init__(self) -> None:
        super().__init__(Path("/nonexistent-models"))
        self.asked: list[str] = []

    def entry(self, name: str) -> ModelEntry:
        self.asked.append(name)
        return ModelEntry(
            name, "extractor", f"{name}.onnx", "", "", "", {}, {}, keypoint_budget=2048
        )

    def session(self, name: str) -> Any:
        self.asked.append(name)
        return object()


def test_every_preset_is_pinned() -> None:
    assert sorted(BUILDS) == feature_config_names()


@pytest.mark.parametrize("name", sorted(BUILDS))
def test_preset_builds_its_components_from_the_models_it_declares(name: str) -> None:
    store = _SessionlessStore()
    extractor, matcher = build_features(FEATURE_CONFIGS[name], store)
    assert (extractor.name, matcher.name) == BUILDS[name]
    assert tuple(dict.fromkeys(store.asked)) == FEATURE_CONFIGS[name].models


@pytest.mark.parametrize("name", sorted(BUILDS))
def test_preset_without_its_models_is_refused(name: str, tmp_path: Path) -> None:
    config = FEATURE_CONFIGS[name]
    if not config.models:
        localizer = build_localizer(EngineConfig.resolve(tmp_path, 40_000_000, name))
        assert (localizer.extractor.name, localizer.matcher.name) == BUILDS[name]
        return
    with pytest.raises(ModelsMissingError, match=f"--models {config.models[0]}`"):
        build_localizer(EngineConfig.resolve(tmp_path, 40_000_000, name))


def test_unknown_name_lists_the_known_ones() -> None:
    with pytest.raises(UnknownComponentError, match="known: auto, aliked, aliked-fast"):
        get_feature_config("superpoint")


def test_auto_prefers_the_models_of_the_preferred_preset() -> None:
    assert PREFERRED_MODELS == ("xfeat", "lighterglue-xfeat")
    assert FEATURE_CONFIGS[PREFERRED_FEATURES].models == PREFERRED_MODELS


class TestModelsForFeatures:
    """``slloc models build --features``: presets and sets resolved through the table."""

    def test_presets_give_their_models_in_order_each_once(self) -> None:
        assert models_for_features(["xfeat-lg", "aliked", "aliked-fast", "xfeat"]) == (
            "xfeat",
            "lighterglue-xfeat",
            "aliked-n16",
            "lightglue-aliked",
        )

    def test_sift_needs_none(self) -> None:
        assert models_for_features(["sift"]) == ()

    def test_auto_is_every_preset_auto_may_pick(self) -> None:
        assert models_for_features([AUTO]) == models_for_features(AUTO_CHOICES)
        assert models_for_features([AUTO])[: len(PREFERRED_MODELS)] == PREFERRED_MODELS

    def test_all_is_every_preset(self) -> None:
        assert set(models_for_features(["all"])) == {
            m for c in FEATURE_CONFIGS.values() for m in c.models
        }

    def test_unknown_name_lists_the_known_ones(self) -> None:
        with pytest.raises(ValueError, match="'superpoint'; known: auto, all, aliked, "):
            models_for_features(["xfeat-lg", "superpoint"])

    def test_cli_builds_the_models_of_the_presets(
        self, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
    ) -> None:
        built: list[tuple[str, ...]] = []
        monkeypatch.setattr(cli, "_missing_modules", lambda *names: [])
        monkeypatch.setattr(build, "build_models", lambda _dir, names, force: built.append(names))
        args = ["models", "build", "--models-dir", str(tmp_path)]
        assert main([*args, "--features", "disk,xfeat-lg", "--models", "aliked-n32,xfeat"]) == 0
        assert main(args) == 0
        assert built == [
            ("disk", "lightglue-disk", "xfeat", "lighterglue-xfeat", "aliked-n32"),
            PREFERRED_MODELS,
        ]

    def test_cli_refuses_an_unknown_preset(self, capsys: pytest.CaptureFixture[str]) -> None:
        assert main(["models", "build", "--features", "superpoint"]) == 1
        assert "unknown feature configuration 'superpoint'" in capsys.readouterr().err


def test_lightglue_settings_need_lightglue() -> None:
    with pytest.raises(ValueError, match="need lightglue"):
        FeatureConfig("x", "aliked-n16", "", lightglue_pairs=3)
    with pytest.raises(ValueError, match="lightglue_pairs"):
        FeatureConfig("x", "aliked-n16", "", lightglue="lightglue-aliked", lightglue_pairs=0)


def test_settings_help_lists_every_preset() -> None:
    help_text = Settings.model_fields["features"].description or ""
    assert Settings.model_fields["features"].default == AUTO
    assert f"one of {', '.join(feature_config_names())};" in help_text


def test_cli_prints_the_table(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["features"]) == 0
    out = capsys.readouterr().out
    assert out == feature_table()
    assert len(out.splitlines()) == 2 + len(FEATURE_CONFIGS)


def test_models_page_holds_the_table() -> None:
    assert feature_table() in MODELS_PAGE.read_text(), (
        "docs/models.md's table of feature configurations is stale: paste `slloc features` over it"
    )
