"""The documentation stays true to the code: the configuration page is the generator's output,
every environment variable the code, scripts and container files read is on it, and the README
keeps the blocks CI runs (``scripts/check_serve.sh``)."""

from __future__ import annotations

import re
from pathlib import Path

from app.settings import Settings
from tools.docs.config_page import OTHER_VARIABLES, PAGE, render

ROOT = Path(__file__).resolve().parents[1]

# os.environ.get("X"), os.environ["X"], os.getenv("X")
_PYTHON_READ = re.compile(r"""(?:environ\.get\(|environ\[|getenv\()\s*["']([A-Z][A-Z0-9_]*)["']""")
# ${X:-default}, ${X:?message}, ${X-default}: a variable that may come from the environment
_SHELL_READ = re.compile(r"\$\{([A-Z][A-Z0-9_]*)(?::?[-?])")
_SLLOC_NAME = re.compile(r"\bSLLOC_[A-Z0-9_]*[A-Z0-9]\b")


def _documented() -> set[str]:
    prefix = str(Settings.model_config.get("env_prefix", ""))
    return {f"{prefix}{name.upper()}" for name in Settings.model_fields} | {
        variable for variable, *_ in OTHER_VARIABLES
    }


def _read_variables() -> dict[str, set[str]]:
    """Variable → the files that read it, over the Python packages, tests, scripts and
    container files."""
    found: dict[str, set[str]] = {}
    python = [
        p for d in ("app", "services", "db", "tools", "tests") for p in (ROOT / d).rglob("*.py")
    ]
    shell = [*(ROOT / "scripts").glob("*.sh"), *(ROOT / "docker").iterdir()]
    for path in python:
        if path.resolve() == Path(__file__).resolve():
            continue
        for name in _PYTHON_READ.findall(path.read_text()):
            found.setdefault(name, set()).add(str(path.relative_to(ROOT)))
    for path in shell:
        if not path.is_file():
            continue
        # comments name variables without reading them
        text = "\n".join(
            line for line in path.read_text().splitlines() if not line.lstrip().startswith("#")
        )
        for name in {*_SHELL_READ.findall(text), *_SLLOC_NAME.findall(text)}:
            found.setdefault(name, set()).add(str(path.relative_to(ROOT)))
    return found


def test_configuration_page_is_current() -> None:
    assert PAGE.read_text() == render(), (
        "docs/configuration.md is stale: run `python -m tools.docs.config_page`"
    )


def test_every_setting_has_a_description() -> None:
    missing = [name for name, field in Settings.model_fields.items() if not field.description]
    assert not missing, f"settings without a description: {missing}"


def test_every_environment_variable_read_is_documented() -> None:
    undocumented = {
        name: sorted(files)
        for name, files in _read_variables().items()
        if name not in _documented()
    }
    assert not undocumented, (
        "environment variables read but not on docs/configuration.md (add them to "
        f"tools/docs/config_page.py OTHER_VARIABLES or to the settings): {undocumented}"
    )


def test_the_scan_finds_the_known_readers() -> None:
    found = _read_variables()
    assert "SLLOC_TORCH_INDEX_URL" in found  # scripts/build_models.sh
    assert "MALLOC_ARENA_MAX" in found  # scripts/serve.sh
    assert "SLLOC_TEST_POSTGRES_URL" in found  # tests/conftest.py


def test_readme_is_the_front_door() -> None:
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 300
    for marker in ("<!-- serve-command -->", "<!-- example-session -->"):
        after = readme.split(marker, 1)
        assert len(after) == 2 and after[1].lstrip("\n").startswith("```"), marker
