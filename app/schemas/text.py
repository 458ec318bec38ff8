"""Free text as it crosses the API: no control characters (NUL cannot be stored in
PostgreSQL; a newline or an escape sequence would forge or garble log lines)."""

from __future__ import annotations

import unicodedata
from typing import Annotated

from pydantic import AfterValidator, Field

# control characters (C0, DEL, C1) and the Unicode line and paragraph separators
_REFUSED = ("Cc", "Zl", "Zp")


def _refuse_control(allowed: str) -> AfterValidator:
    def check(value: str) -> str:
        for char in value:
            if char not in allowed and unicodedata.category(char) in _REFUSED:
                raise ValueError(f"must not contain control characters (found U+{ord(char):04X})")
        return value

    return AfterValidator(check)


Name = Annotated[str, Field(min_length=1, max_length=255), _refuse_control("")]
"""A name: one line of printable text."""

Description = Annotated[str, Field(max_length=10_000), _refuse_control("\t\n\r")]
"""Free text: printable, with tabs and line breaks."""
