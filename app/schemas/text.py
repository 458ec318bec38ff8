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


# bidirectional formatting characters (Unicode category Cf): an override or isolate makes a
# name display other than it reads (U+202E shows "exe.txt" as "txt.exe")
_BIDI_CONTROLS = frozenset(
    "\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069"
)


def _refuse_bidi_and_blank(value: str) -> str:
    for char in value:
        if char in _BIDI_CONTROLS:
            raise ValueError(
                f"must not contain bidirectional control characters (found U+{ord(char):04X})"
            )
    if not value.strip():
        raise ValueError("must not be blank (only spaces)")
    return value


# The same rule as JSON Schema patterns, so the OpenAPI document states it; the validators
# above answer (Cc is U+0000–U+001F and U+007F–U+009F, Zl U+2028, Zp U+2029).
# a name also needs one character that is not a space (str.isspace) and has no bidirectional
# controls
NAME_PATTERN = (
    r"^(?=.*[^\u0020\u00a0\u1680\u2000-\u200a\u202f\u205f\u3000])"
    r"[^\u0000-\u001f\u007f-\u009f\u2028\u2029\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*$"
)
DESCRIPTION_PATTERN = r"^[^\u0000-\u0008\u000b\u000c\u000e-\u001f\u007f-\u009f\u2028\u2029]*$"

Name = Annotated[
    str,
    Field(min_length=1, max_length=255, json_schema_extra={"pattern": NAME_PATTERN}),
    _refuse_control(""),
    AfterValidator(_refuse_bidi_and_blank),
]
"""A name: one line of printable text, not only spaces, without bidirectional controls."""

Description = Annotated[
    str,
    Field(max_length=10_000, json_schema_extra={"pattern": DESCRIPTION_PATTERN}),
    _refuse_control("\t\n\r"),
]
"""Free text: printable, with tabs and line breaks."""
