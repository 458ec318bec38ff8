"""Reference / query split of a dataset by rules or by explicit name lists.

A rule is space- or comma-separated tokens, all of which an image must satisfy:
``range:A-B`` (dataset positions A…B inclusive), ``every:N`` (every Nth position from the
range's start), ``list:FILE`` (names listed in FILE, one a line), ``rest`` (images the other
side does not take; only one side may say it). ``all`` (or an empty rule) takes everything.
Example: ``--references "range:0-499 every:5" --queries "range:500-999 every:10"``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from tools.evaluation.datasets import Dataset, PosedImage

# the split of datasets that suggest none: every 10th image is a query, the rest the map
DEFAULT_REFERENCES = "rest"
DEFAULT_QUERIES = "every:10"


@dataclass(frozen=True)
class Split:
    references: list[PosedImage]
    queries: list[PosedImage]


def _tokens(rule: str) -> list[str]:
    return [t for t in re.split(r"[\s,]+", rule.strip()) if t and t != "all"]


def _select(images: list[PosedImage], rule: str, exclude: set[str]) -> list[PosedImage]:
    start, stop, step = 0, len(images) - 1, 1
    names: set[str] | None = None
    rest = False
    for token in _tokens(rule):
        kind, _, value = token.partition(":")
        try:
            if kind == "range":
                a, _, b = value.partition("-")
                start, stop = int(a), int(b)
            elif kind == "every":
                step = int(value)
                if step < 1:
                    raise ValueError
            elif kind == "list":
                names = {
                    line.strip() for line in Path(value).read_text().splitlines() if line.strip()
                }
            elif kind == "rest":
                rest = True
            else:
                raise ValueError
        except ValueError:
            raise ValueError(
                f"bad split token {token!r}: use range:A-B, every:N, list:FILE, rest or all"
            ) from None
    chosen = [
        image
        for i, image in enumerate(images)
        if start <= i <= stop
        and (i - start) % step == 0
        and (names is None or image.name in names)
        and not (rest and image.name in exclude)
    ]
    if names is not None:
        missing = names - {image.name for image in images}
        if missing:
            raise ValueError(f"listed names not in the dataset: {sorted(missing)[:5]}")
    return chosen


def split_dataset(
    dataset: Dataset, references: str | None = None, queries: str | None = None
) -> Split:
    """Apply the rules (``None``: the dataset's suggestion, else the generic default).

    Raises:
        ValueError: a bad rule, both sides say ``rest``, or a side ends up empty.
    """
    ref_rule = references or dataset.default_references or DEFAULT_REFERENCES
    query_rule = queries or dataset.default_queries or DEFAULT_QUERIES
    ref_rest, query_rest = "rest" in _tokens(ref_rule), "rest" in _tokens(query_rule)
    if ref_rest and query_rest:
        raise ValueError("only one of references and queries may say 'rest'")
    if ref_rest:
        query_images = _select(dataset.images, query_rule, set())
        ref_images = _select(dataset.images, ref_rule, {i.name for i in query_images})
    else:
        ref_images = _select(dataset.images, ref_rule, set())
        query_images = _select(dataset.images, query_rule, {i.name for i in ref_images})
    if not ref_images or not query_images:
        raise ValueError(
            f"the split leaves {len(ref_images)} references and {len(query_images)} queries"
        )
    return Split(ref_images, query_images)
