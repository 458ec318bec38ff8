"""Request bodies are admitted within the body memory (``SLLOC_BODY_MEMORY_MIB``): a body
that does not fit beside those in flight gets 503 with Retry-After, and the memory returns
when each answer has been sent, also after the app failed."""

from __future__ import annotations

import asyncio
from pathlib import Path

import httpx
import pytest
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse
from starlette.routing import Route

from app.limits import BodyMemory, BodySizeLimit, body_cost
from app.main import create_app
from app.settings import Settings
from services.runtime.memory import JSON_BODY_FACTOR


def test_cost_is_the_declared_length_json_parsed_whole() -> None:
    assert body_cost({b"content-length": b"1000"}, 10**6) == 1000
    json_body = {b"content-length": b"1000", b"content-type": b"application/json"}
    assert body_cost(json_body, 10**6) == int(1000 * JSON_BODY_FACTOR)
    assert body_cost({b"transfer-encoding": b"chunked"}, 10**6) == 10**6
    assert body_cost({}, 10**6) == 0  # a GET


def _held_app(memory: BodyMemory, release: asyncio.Event, entered: asyncio.Event) -> object:
    async def hold(request: Request) -> JSONResponse:
        body = await request.body()
        if request.query_params.get("fail"):
            raise RuntimeError("the handler failed")
        if request.query_params.get("hold"):
            entered.set()
            await release.wait()
        return JSONResponse({"bytes": len(body), "held": memory.held_bytes})

    app = Starlette(routes=[Route("/", hold, methods=["POST"])])
    return BodySizeLimit(app, max_bytes=1000, memory=memory)


@pytest.mark.anyio
async def test_a_body_past_the_memory_waits_its_turn() -> None:
    memory = BodyMemory(budget_bytes=1000)
    release, entered = asyncio.Event(), asyncio.Event()
    transport = httpx.ASGITransport(app=_held_app(memory, release, entered))  # type: ignore[arg-type]
    async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
        held = asyncio.create_task(client.post("/?hold=1", content=b"x" * 700))
        await entered.wait()
        assert memory.held_bytes == 700
        busy = await client.post("/", content=b"y" * 400)
        assert busy.status_code == 503
        assert busy.headers["retry-after"] == "1"
        assert busy.headers["content-type"] == "application/problem+json"
        assert busy.json()["type"].endswith("/body-memory-full")
        fits = await client.post("/", content=b"z" * 300)  # 700 + 300 fit
        assert fits.status_code == 200 and fits.json() == {"bytes": 300, "held": 1000}
        release.set()
        assert (await held).status_code == 200
        assert memory.held_bytes == 0
        after = await client.post("/", content=b"y" * 400)
        assert after.status_code == 200
        with pytest.raises(RuntimeError):
            await client.post("/?fail=1", content=b"y" * 400)
        assert memory.held_bytes == 0


def test_the_service_holds_bodies_to_its_setting(tmp_path: Path) -> None:
    settings = Settings(
        database_url=f"sqlite:///{tmp_path}/body.db",
        features="sift",
        max_upload_bytes=1024 * 1024,
        body_memory_mib=6,
    )
    app = create_app(settings)
    [limit] = [m for m in app.user_middleware if m.cls is BodySizeLimit]
    assert limit.kwargs["max_bytes"] == 3 * 1024 * 1024
    assert limit.kwargs["memory"].budget_bytes == 6 * 1024 * 1024
