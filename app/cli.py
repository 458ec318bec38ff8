"""The server's own commands, which the ``slloc`` CLI (``tools/cli.py``) registers: ``serve``
(the HTTP API under uvicorn) and ``db upgrade`` (the schema to the newest revision)."""

from __future__ import annotations

import argparse
from typing import Any

from app.logs import configure_logging
from app.settings import get_settings

SERVER_COMMANDS = ("serve", "db")


def add_serve_parser(sub: argparse._SubParsersAction[Any]) -> None:
    serve = sub.add_parser("serve", help="run the HTTP API")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8000)
    serve.add_argument(
        "--log-level",
        default="info",
        choices=("critical", "error", "warning", "info", "debug", "trace"),
        help="the least severe records written (the access lines are info)",
    )


def add_db_parser(sub: argparse._SubParsersAction[Any]) -> None:
    db = sub.add_parser("db", help="database maintenance")
    db_sub = db.add_subparsers(dest="db_command", required=True)
    db_sub.add_parser("upgrade", help="migrate the schema to the newest revision")


def run_server_command(args: argparse.Namespace) -> int:
    """Run ``serve`` or ``db upgrade`` (``args.command`` one of ``SERVER_COMMANDS``)."""
    if args.command == "serve":
        return serve(args.host, args.port, args.log_level)
    configure_logging("text")
    return db_upgrade()


def serve(host: str, port: int, log_level: str) -> int:
    import uvicorn
    from uvicorn.config import LOG_LEVELS

    from app.main import create_app
    from app.slow_clients import MAX_REQUEST_HEAD_BYTES, ClientAdmission, IdleConnectionGuard

    settings = get_settings()
    configure_logging(settings.log_format, LOG_LEVELS[log_level])
    app = ClientAdmission(
        create_app(settings),
        max_in_flight=settings.limit_concurrency,
        max_per_client=settings.max_requests_per_client,
        body_timeout_s=settings.request_body_timeout_s,
    )
    uvicorn.run(
        app,
        host=host,
        port=port,
        log_level=log_level,
        # uvicorn's records go to the handler above; the app writes the access lines
        log_config=None,
        access_log=False,
        http=IdleConnectionGuard,
        timeout_keep_alive=settings.timeout_keep_alive_s,
        # admission is the app's (ClientAdmission): uvicorn's counts idle connections too
        limit_concurrency=None,
        h11_max_incomplete_event_size=MAX_REQUEST_HEAD_BYTES,
    )
    return 0


def db_upgrade() -> int:
    from db.migrate import upgrade
    from db.session import make_engine

    engine = make_engine(get_settings().database_url)
    upgrade(engine)
    print(f"database at {engine.url.render_as_string(hide_password=True)} is at head")
    return 0
