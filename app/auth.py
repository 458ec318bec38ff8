"""API-key roles: the per-route requirement, and a gate that enforces it before the request
body is read (a request without a valid key is answered 401 whatever its body holds)."""

from __future__ import annotations

import hmac
from collections.abc import Sequence
from typing import Annotated

from fastapi import Request, Security
from fastapi.routing import APIRoute
from fastapi.security import APIKeyHeader
from starlette.routing import BaseRoute, Match
from starlette.types import ASGIApp, Receive, Scope, Send

from app.errors import ProblemError, problem_response
from app.settings import Role, Settings

API_KEY_HEADER = "X-API-Key"

_api_key_header = APIKeyHeader(name=API_KEY_HEADER, auto_error=False)


def role_of(settings: Settings, key: str | None) -> Role | None:
    """The role of API key ``key``; None for no key or an unknown one."""
    if key is None:
        return None
    for candidate in settings.parsed_api_keys():
        if hmac.compare_digest(candidate.key.get_secret_value().encode(), key.encode()):
            return candidate.role
    return None


class RoleCheck:
    """A route dependency: the request's API key must have one of ``allowed`` roles (nothing
    is checked while auth is off). ``ApiKeyGate`` runs the same check before the body."""

    def __init__(self, allowed: tuple[Role, ...]) -> None:
        self.allowed = allowed

    async def __call__(
        self, request: Request, key: Annotated[str | None, Security(_api_key_header)]
    ) -> None:
        self.check(request.app.state.settings, key)

    def check(self, settings: Settings, key: str | None) -> None:
        """Raises:
        ProblemError: 401 for a missing or unknown key, 403 for a role not allowed.
        """
        if not settings.api_keys:
            return  # auth is off; the app logged a warning at start-up
        role = role_of(settings, key)
        if role is None:
            raise ProblemError(401, "unauthorized", "Unauthorized", "missing or unknown X-API-Key")
        if role not in self.allowed:
            raise ProblemError(
                403, "forbidden", "Forbidden", f"this needs the {' or '.join(self.allowed)} role"
            )


class ApiKeyGate:
    """ASGI middleware: answers 401/403 for a request to one of ``routes`` with a
    ``RoleCheck`` before the route reads its body, so a bad body never speaks before a bad
    key."""

    def __init__(self, app: ASGIApp, routes: Sequence[BaseRoute]) -> None:
        self.app = app
        self.checks = [
            (route, dependency.dependency)
            for route in routes
            if isinstance(route, APIRoute)
            for dependency in route.dependencies
            if isinstance(dependency.dependency, RoleCheck)
        ]

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            check = next(
                (check for route, check in self.checks if route.matches(scope)[0] is Match.FULL),
                None,
            )
            if check is not None:
                request = Request(scope, receive)
                try:
                    check.check(request.app.state.settings, request.headers.get(API_KEY_HEADER))
                except ProblemError as exc:
                    headers = {"WWW-Authenticate": API_KEY_HEADER} if exc.status == 401 else None
                    response = problem_response(
                        request, exc.status, exc.slug, exc.title, exc.detail or exc.title, headers
                    )
                    await response(scope, receive, send)
                    return
        await self.app(scope, receive, send)
