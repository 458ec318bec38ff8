"""``manifest.json`` in the models directory: what was exported, from which weights, how.

One entry per ONNX file. The server trusts a model only when its file's sha256 matches the
manifest, so a half-written or swapped file is refused instead of served.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

MANIFEST_NAME = "manifest.json"
ModelKind = Literal["extractor", "matcher", "global_descriptor"]


@dataclass(frozen=True)
class ModelEntry:
    """name: unique model name (``aliked-n16``, ``lightglue-aliked``, …).
    kind: what it does. file: ONNX file name relative to the models directory.
    sha256: of that file. source_weights / source_sha256: the weights it was exported from.
    inputs / outputs: tensor name → ``{"dtype": ..., "shape": [...]}`` (symbolic dims as str).
    keypoint_budget: default keypoints per image (extractors), else None.
    config: anything else the runtime needs (descriptor size, resize policy, ...).
    """

    name: str
    kind: ModelKind
    file: str
    sha256: str
    source_weights: str
    source_sha256: str
    inputs: dict[str, Any]
    outputs: dict[str, Any]
    keypoint_budget: int | None = None
    config: dict[str, Any] = field(default_factory=dict)


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_manifest(models_dir: Path) -> dict[str, ModelEntry]:
    """Entries by name; empty when there is no manifest."""
    path = models_dir / MANIFEST_NAME
    if not path.is_file():
        return {}
    raw = json.loads(path.read_text())
    return {e["name"]: ModelEntry(**e) for e in raw["models"]}


def write_entry(models_dir: Path, entry: ModelEntry) -> None:
    """Add or replace one entry (atomically: write a temporary file, then rename)."""
    models_dir.mkdir(parents=True, exist_ok=True)
    entries = read_manifest(models_dir)
    entries[entry.name] = entry
    path = models_dir / MANIFEST_NAME
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(
        json.dumps(
            {"models": [asdict(e) for e in sorted(entries.values(), key=lambda e: e.name)]},
            indent=2,
        )
        + "\n"
    )
    tmp.replace(path)


def verified_path(models_dir: Path, entry: ModelEntry) -> Path:
    """The entry's file, after checking that it exists and its sha256 matches."""
    path = models_dir / entry.file
    if not path.is_file():
        raise FileNotFoundError(f"{entry.name}: {path} is missing (run `slloc models build`)")
    actual = file_sha256(path)
    if actual != entry.sha256:
        raise ValueError(
            f"{entry.name}: {path} has sha256 {actual[:12]}…, the manifest says "
            f"{entry.sha256[:12]}… (rebuild with `slloc models build`)"
        )
    return path
