"""RFC 9457 problem details for every 4xx/5xx, and the domain-error → status table."""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from sqlalchemy.exc import DBAPIError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.formparsers import MultiPartException
from starlette.routing import BaseRoute, Match, Route
from starlette.types import Scope, Send

from app.request_context import REQUEST_ID_HEADER, current_request_id
from app.usecases.errors import ConflictError, NotFoundError
from app.usecases.served_features import FeaturesUnavailableError
from db.blobs import BlobStoreError
from services.errors import ImageDecodeError, ImageTooLargeError, InvalidInputError

logger = logging.getLogger(__name__)

PROBLEM_JSON = "application/problem+json"
PROBLEM_BASE = "https://slloc.dev/problems/"
# seconds a client is asked to wait after a 503 for an unreachable database
DATABASE_RETRY_AFTER_S = 5
# … and for a blob store that cannot be reached or refuses writes
BLOB_STORE_RETRY_AFTER_S = 5


# SQLite's extended result codes of a write the file system refused: a read-only file or
# folder (an open file made immutable or on a file system remounted read-only fails its
# write() as an I/O error), a full disk
_SQLITE_NOT_WRITABLE = frozenset(
    {
        "SQLITE_FULL",
        "SQLITE_IOERR_WRITE",
        "SQLITE_IOERR_FSYNC",
        "SQLITE_IOERR_DIR_FSYNC",
        "SQLITE_IOERR_TRUNCATE",
        "SQLITE_IOERR_DELETE",
    }
)
# PostgreSQL's SQLSTATEs of the same: read_only_sql_transaction (a hot standby, or
# default_transaction_read_only), disk_full
_POSTGRES_NOT_WRITABLE = frozenset({"25006", "53100"})


def database_not_writable(exc: BaseException) -> bool:
    """Whether a database error is a write the database or its storage refused, while it
    may still serve reads."""
    orig = getattr(exc, "orig", None)
    name = str(getattr(orig, "sqlite_errorname", ""))
    if name.startswith("SQLITE_READONLY") or name in _SQLITE_NOT_WRITABLE:
        return True
    return getattr(orig, "sqlstate", None) in _POSTGRES_NOT_WRITABLE


class Problem(BaseModel):
    """RFC 9457 problem details. ``type`` is a stable URI naming the kind of problem."""

    type: str
    title: str
    status: int
    detail: str | None = None
    instance: str | None = None
    errors: list[dict[str, Any]] | None = None
    request_id: str | None = Field(
        None, description="The request's id, as in its X-Request-ID header and its log lines"
    )


class ProblemError(Exception):
    """Raise anywhere in the app to answer with a problem document."""

    def __init__(
        self,
        status: int,
        slug: str,
        title: str,
        detail: str | None = None,
        errors: list[dict[str, Any]] | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(detail or title)
        self.status = status
        self.slug = slug
        self.title = title
        self.detail = detail
        self.errors = errors
        self.headers = headers


def invalid(detail: str, errors: list[dict[str, Any]] | None = None) -> ProblemError:
    return ProblemError(422, "invalid-input", "Invalid input", detail, errors)


def too_large(detail: str) -> ProblemError:
    return ProblemError(413, "payload-too-large", "Payload too large", detail)


# (status, slug, title) per domain error, most specific first; the detail is the message
_DOMAIN_ERRORS: list[tuple[type[Exception], int, str, str]] = [
    (NotFoundError, 404, "not-found", "Not found"),
    (FeaturesUnavailableError, 409, "feature-models-missing", "Feature models missing"),
    (ConflictError, 409, "conflict", "Conflict"),
    (ImageTooLargeError, 413, "image-too-large", "Image too large"),
    (ImageDecodeError, 422, "invalid-image", "Invalid image"),
    (InvalidInputError, 422, "invalid-input", "Invalid input"),
]

_STATUS_SLUGS = {
    400: ("bad-request", "Bad request"),
    401: ("unauthorized", "Unauthorized"),
    403: ("forbidden", "Forbidden"),
    404: ("not-found", "Not found"),
    405: ("method-not-allowed", "Method not allowed"),
    413: ("payload-too-large", "Payload too large"),
}

PROBLEM_CONTENT: dict[str, Any] = {
    PROBLEM_JSON: {"schema": {"$ref": "#/components/schemas/Problem"}}
}


def problem_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """``responses=`` argument declaring problem documents for these statuses in OpenAPI."""
    return {status: {"description": _describe(status)} for status in statuses}


def document_problems(schema: dict[str, Any]) -> None:
    """Rewrite an OpenAPI document so every 4xx/5xx answer is ``application/problem+json``
    with the ``Problem`` schema (FastAPI would describe 422 as its own JSON shape)."""
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    components["Problem"] = Problem.model_json_schema()
    for name in ("HTTPValidationError", "ValidationError"):
        components.pop(name, None)
    for operations in schema.get("paths", {}).values():
        for operation in operations.values():
            for status, response in operation.get("responses", {}).items():
                if status.startswith(("4", "5")):
                    response["content"] = PROBLEM_CONTENT
                    response["description"] = _describe(int(status))


def _describe(status: int) -> str:
    return {
        400: "Malformed body: JSON that is not UTF-8, or multipart without a boundary",
        401: "Missing or unknown API key",
        403: "The API key's role may not do this",
        404: "Map or image not found",
        409: "Name already taken; or, on a localize, the map's references need feature models "
        "this server lacks (type feature-models-missing)",
        413: "Upload or image too large",
        422: "Invalid input",
        503: "Busy (too many requests in progress or waiting), the database unreachable, or "
        "the blob store unreachable or refusing writes: retry after Retry-After seconds",
    }.get(status, "Problem")


def _response(
    request: Request, problem: Problem, headers: dict[str, str] | None = None
) -> JSONResponse:
    problem.instance = problem.instance or request.url.path
    problem.request_id = current_request_id()
    return JSONResponse(
        problem.model_dump(exclude_none=True),
        status_code=problem.status,
        media_type=PROBLEM_JSON,
        headers=headers,
    )


def problem_response(
    request: Request,
    status: int,
    slug: str,
    title: str,
    detail: str,
    headers: dict[str, str] | None = None,
) -> JSONResponse:
    return _response(
        request,
        Problem(type=PROBLEM_BASE + slug, title=title, status=status, detail=detail),
        headers,
    )


def _part_too_large(exc: StarletteHTTPException) -> bool:
    """Whether ``exc`` is the form parser refusing a text part over its size limit (raised
    as a 400 while handling the parser's ``MultiPartException``)."""
    cause = exc.__context__
    return isinstance(cause, MultiPartException) and "exceeded maximum size" in cause.message


def _allowed_methods(routes: Sequence[BaseRoute], scope: Scope) -> str:
    """The methods of every route at the request's path (the router names only the first
    route's)."""
    methods: set[str] = set()
    for route in routes:
        if isinstance(route, Route) and route.methods and route.matches(scope)[0] is Match.PARTIAL:
            methods |= route.methods
    return ", ".join(sorted(methods))


def install_error_handlers(app: FastAPI, routes: Sequence[BaseRoute]) -> None:
    """Problem documents for every error; ``routes`` are the API's (a 405's ``Allow`` names
    the methods of all of them at the path)."""

    @app.exception_handler(ProblemError)
    async def _problem(request: Request, exc: ProblemError) -> JSONResponse:
        headers = dict(exc.headers or {})
        if exc.status == 401:
            headers["WWW-Authenticate"] = "X-API-Key"
        return _response(
            request,
            Problem(
                type=PROBLEM_BASE + exc.slug,
                title=exc.title,
                status=exc.status,
                detail=exc.detail,
                errors=exc.errors,
            ),
            headers,
        )

    async def _domain(request: Request, exc: Exception) -> JSONResponse:
        for cls, status, slug, title in _DOMAIN_ERRORS:
            if isinstance(exc, cls):
                return problem_response(request, status, slug, title, str(exc))
        raise exc  # pragma: no cover - installed for the table's classes only

    for domain_error, *_ in _DOMAIN_ERRORS:
        app.add_exception_handler(domain_error, _domain)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [
            {"loc": list(e.get("loc", ())), "msg": e.get("msg", ""), "type": e.get("type", "")}
            for e in exc.errors()
        ]
        return _response(
            request,
            Problem(
                type=PROBLEM_BASE + "invalid-input",
                title="Invalid input",
                status=422,
                detail="; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors),
                errors=errors,
            ),
        )

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        status = 413 if exc.status_code == 400 and _part_too_large(exc) else exc.status_code
        slug, title = _STATUS_SLUGS.get(status, ("error", "Error"))
        headers = dict(exc.headers or {})
        if status == 405:
            headers["Allow"] = _allowed_methods(routes, request.scope) or headers.get("Allow", "")
        return problem_response(request, status, slug, title, str(exc.detail), headers or None)

    async def _database_down(request: Request, exc: Exception) -> JSONResponse:
        """The database is unreachable (connection refused or lost, pool exhausted, a
        locked file) or refuses writes (a read-only file, folder or server, a full disk):
        503 to retry, not a 500."""
        if database_not_writable(exc):
            kind, title, detail = (
                "database-not-writable",
                "Database not writable",
                "the database refuses writes (read-only file or folder, read-only server or "
                "full disk); reads are still served",
            )
        elif (
            isinstance(exc, DBAPIError)
            and not isinstance(exc, OperationalError)
            and not exc.connection_invalidated
        ):
            return await _unexpected(request, exc)
        else:
            kind, title = "database-unavailable", "Database unavailable"
            detail = "the database cannot be reached"
        logger.warning(
            "%s on %s %r: %s",
            title.lower(),
            request.method,
            request.url.path,
            str(getattr(exc, "orig", None) or exc).splitlines()[0][:200],
        )
        return problem_response(
            request,
            503,
            kind,
            title,
            f"{detail}; retry after {DATABASE_RETRY_AFTER_S} s",
            {"Retry-After": str(DATABASE_RETRY_AFTER_S)},
        )

    for database_error in (OperationalError, DBAPIError, PoolTimeoutError):
        app.add_exception_handler(database_error, _database_down)

    @app.exception_handler(BlobStoreError)
    async def _blob_store_down(request: Request, exc: BlobStoreError) -> JSONResponse:
        """The blob store of the originals cannot be reached (an S3 endpoint down or
        answering with an error) or refuses a write (a read-only or full folder): 503 to
        retry, not a 500. An add that fails so stored nothing (its blobs come before its
        row)."""
        logger.warning(
            "blob store unavailable on %s %r: %s",
            request.method,
            request.url.path,
            str(exc).splitlines()[0][:300],
        )
        if request.method in ("GET", "HEAD"):
            what = (
                "cannot be reached or refuses the read (S3 endpoint down or refusing, an I/O error)"
            )
        else:
            what = (
                "cannot be reached or refuses writes (read-only or full folder, S3 endpoint "
                "down or refusing); nothing was stored"
            )
        return problem_response(
            request,
            503,
            "blob-store-unavailable",
            "Blob store unavailable",
            f"the blob store that keeps the originals of reference images {what}; retry "
            f"after {BLOB_STORE_RETRY_AFTER_S} s",
            {"Retry-After": str(BLOB_STORE_RETRY_AFTER_S)},
        )

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        logger.exception("unhandled error on %s %r", request.method, request.url.path)
        # the server drops the connection after an unhandled error; say so. This answer is
        # sent outside the middleware that echoes the request id.
        headers = {"Connection": "close"}
        request_id = current_request_id()
        if request_id is not None:
            headers[REQUEST_ID_HEADER] = request_id
        return problem_response(
            request,
            500,
            "internal-error",
            "Internal server error",
            "an unexpected error occurred",
            headers,
        )


async def send_problem_and_close(
    scope: Scope,
    send: Send,
    status: int,
    kind: str,
    title: str,
    detail: str,
    headers: Sequence[tuple[bytes, bytes]] = (),
) -> None:
    """Answers a problem+json from ASGI middleware, outside the exception handlers, and
    closes the connection (the request's body is left unread)."""
    body = json.dumps(
        {
            "type": PROBLEM_BASE + kind,
            "title": title,
            "status": status,
            "detail": detail,
            "instance": scope.get("path", ""),
            "request_id": current_request_id(),
        }
    ).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", PROBLEM_JSON.encode()),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
                *headers,
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})
