"""Errors raised by the client: every non-2xx answer becomes a :class:`ProblemError`."""

from __future__ import annotations

import contextlib
from datetime import UTC, datetime
from email.utils import parsedate_to_datetime
from typing import Any

import httpx

from slloc_client.models import Problem


class SllocError(Exception):
    """Base class of the client's errors."""


class ProblemError(SllocError):
    """A non-2xx answer, as its RFC 9457 problem (``application/problem+json``).

    ``type`` is the stable URI naming the kind of problem (compare it, not ``title``);
    ``errors`` lists the fields a 422 refused; ``request_id`` matches the server's log lines;
    ``retry_after`` is the ``Retry-After`` header in seconds, when the answer had one. An answer
    that is not a problem document (e.g. a proxy's HTML error page) gets ``type``
    ``about:blank``, the status's reason phrase as ``title`` and the start of its body as
    ``detail``.
    """

    def __init__(self, problem: Problem, response: httpx.Response | None = None):
        self.problem = problem
        self.response = response
        self.retry_after = retry_after_s(response) if response is not None else None
        message = f"{problem.status} {problem.title}"
        if problem.detail:
            message += f": {problem.detail}"
        super().__init__(message)

    @property
    def type(self) -> str:
        return self.problem.type

    @property
    def title(self) -> str:
        return self.problem.title

    @property
    def status(self) -> int:
        return self.problem.status

    @property
    def detail(self) -> str | None:
        return self.problem.detail

    @property
    def instance(self) -> str | None:
        return self.problem.instance

    @property
    def errors(self) -> list[dict[str, Any]] | None:
        return self.problem.errors

    @property
    def request_id(self) -> str | None:
        return self.problem.request_id

    @classmethod
    def from_response(cls, response: httpx.Response) -> ProblemError:
        """The problem a non-2xx ``response`` carries (read: ``response.read()`` done)."""
        problem: Problem | None = None
        with contextlib.suppress(ValueError):  # not JSON, or not a problem document
            body = response.json()
            if isinstance(body, dict):
                problem = Problem.model_validate({"status": response.status_code, **body})
        if problem is None:
            problem = Problem(
                type="about:blank",
                title=response.reason_phrase or f"HTTP {response.status_code}",
                status=response.status_code,
                detail=response.text[:500] or None,
            )
        if problem.request_id is None and "X-Request-ID" in response.headers:
            problem = problem.model_copy(update={"request_id": response.headers["X-Request-ID"]})
        return cls(problem, response)


def retry_after_s(response: httpx.Response) -> float | None:
    """``Retry-After`` in seconds (delay-seconds or an HTTP date); None when absent or
    unreadable."""
    value = response.headers.get("Retry-After")
    if value is None:
        return None
    value = value.strip()
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        when = parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return max(0.0, (when - datetime.now(UTC)).total_seconds())
