"""Log records with the request id, written as text or as JSON lines; neither lets a user
string start a line of its own."""

from __future__ import annotations

import copy
import json
import logging
import sys
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any

from app.request_context import current_request_id
from app.settings import LogFormat

# ``request_tag``: " [<request id>]", or nothing outside a request
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s%(request_tag)s: %(message)s"

# the access line's fields (``app.request_context``), written as JSON members
ACCESS_FIELDS = ("method", "path", "status", "duration_ms")

# C0 and C1 control characters, DEL, and the Unicode line and paragraph separators
_CONTROL = {
    code: repr(chr(code))[1:-1] for code in (*range(0x20), *range(0x7F, 0xA0), 0x2028, 0x2029)
}


def escape_control(text: str) -> str:
    """``text`` with every control character written as its Python escape (``\\n``,
    ``\\x1b``, ``\\u2028``), so that it stays on one line."""
    return text.translate(_CONTROL)


class _RequestIdRecords:
    """Log record factory: the wrapped factory's record, with ``request_id`` set to the id of
    the request being handled (None outside one)."""

    def __init__(self, wrapped: Callable[..., logging.LogRecord]) -> None:
        self.wrapped = wrapped

    def __call__(self, *args: Any, **kwargs: Any) -> logging.LogRecord:
        record = self.wrapped(*args, **kwargs)
        record.request_id = current_request_id()
        return record


def install_request_id_records() -> None:
    """Give every log record a ``request_id`` attribute (once per process)."""
    factory = logging.getLogRecordFactory()
    if not isinstance(factory, _RequestIdRecords):
        logging.setLogRecordFactory(_RequestIdRecords(factory))


class TextFormatter(logging.Formatter):
    """``time level logger [request id]: message`` (no ``[request id]`` outside a request).
    Control characters in the message are escaped and the lines of a traceback indented, so
    every line that starts in the first column starts a record."""

    def __init__(self) -> None:
        super().__init__(TEXT_FORMAT)

    def formatMessage(self, record: logging.LogRecord) -> str:
        shown = copy.copy(record)  # other handlers see the record as it was
        shown.message = escape_control(record.message)
        request_id = getattr(record, "request_id", None)
        shown.request_tag = f" [{request_id}]" if request_id else ""
        return super().formatMessage(shown)

    def formatException(self, ei: Any) -> str:
        return _indented(super().formatException(ei))

    def formatStack(self, stack_info: str) -> str:
        return _indented(super().formatStack(stack_info))


def _indented(text: str) -> str:
    return "\n".join("    " + escape_control(line) for line in text.splitlines())


class JsonFormatter(logging.Formatter):
    """One JSON object per record: time (ISO 8601, UTC), level, logger, message,
    request_id, the access line's fields when present, and exception and stack when
    present. JSON escapes every control character, so a record is always one line."""

    def format(self, record: logging.LogRecord) -> str:
        document: dict[str, Any] = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
            "request_id": getattr(record, "request_id", None),
        }
        for field in ACCESS_FIELDS:
            if hasattr(record, field):
                document[field] = getattr(record, field)
        if record.exc_info:
            document["exception"] = self.formatException(record.exc_info)
        if record.stack_info:
            document["stack"] = self.formatStack(record.stack_info)
        return json.dumps(document, default=str)


def configure_logging(log_format: LogFormat, level: int = logging.INFO) -> None:
    """Send every record of ``level`` and above to stderr as ``log_format``, with its request
    id; like ``logging.basicConfig``, nothing changes when the root logger has a handler.
    Python warnings (numpy's RuntimeWarnings among them) become records of the
    ``py.warnings`` logger, so they come out in the same format instead of as raw stderr."""
    install_request_id_records()
    logging.captureWarnings(True)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if log_format == "json" else TextFormatter())
    logging.basicConfig(level=level, handlers=[handler])
