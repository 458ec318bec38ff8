"""The published patterns of names and descriptions refuse exactly what the validators do."""

from __future__ import annotations

import re
import sys

import pytest
from pydantic import TypeAdapter, ValidationError

from app.schemas.text import DESCRIPTION_PATTERN, NAME_PATTERN, Description, Name


@pytest.mark.parametrize(
    ("kind", "pattern"), [(Name, NAME_PATTERN), (Description, DESCRIPTION_PATTERN)]
)
def test_pattern_matches_the_validator(kind: object, pattern: str) -> None:
    adapter = TypeAdapter(kind)
    compiled = re.compile(pattern)
    for code in range(sys.maxunicode + 1):
        if 0xD800 <= code <= 0xDFFF:
            continue  # a lone surrogate is no text: refused as a string before any rule
        char = chr(code)
        try:
            adapter.validate_python(char)
            valid = True
        except ValidationError:
            valid = False
        # fullmatch: in Python `$` also matches before a final newline, in JSON Schema not
        assert valid == bool(compiled.fullmatch(char)), f"U+{code:04X}"
