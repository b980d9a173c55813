"""Shared fixtures and helpers.

GPU tests are generated per backend: they skip where no CUDA device is present, unless
CLOTHBALL_REQUIRE_GPU=1, which turns those skips into failures. The server helpers (a real
server on loopback, port 0, and real clients) serve the server, client and Falcon tests.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import urllib.error
import urllib.request
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any, TypeVar

import pytest
from clothball.game import cuda_unavailable_reason
from clothball.game.sim.scene import Scene
from clothball.server.app import GameServer
from clothball.server.room import RoomSettings
from clothball.server.thread import ServerThread

REQUIRE_GPU = os.environ.get("CLOTHBALL_REQUIRE_GPU", "") not in ("", "0")


def require_cuda() -> None:
    why = cuda_unavailable_reason()
    if why:
        if REQUIRE_GPU:
            pytest.fail(f"CLOTHBALL_REQUIRE_GPU=1 but the CUDA backend is unavailable: {why}")
        pytest.skip(f"no CUDA backend: {why}")


@pytest.fixture(params=["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def backend(request: pytest.FixtureRequest) -> str:
    if request.param == "cuda":
        require_cuda()
    return request.param


@pytest.fixture
def cuda() -> str:
    """The CUDA backend, for tests of it alone."""
    require_cuda()
    return "cuda"


@pytest.fixture(params=["float32", "float64"])
def precision(request: pytest.FixtureRequest) -> str:
    return request.param


# --- a real server on loopback and real clients ---------------------------------------



T = TypeVar("T")

# A small cloth keeps the room threads cheap on a 2-core machine.
TINY = Scene.load("classic").with_changes({"cloth": {"n": 16}})
TINY.name = "tiny"

# Rounds that end fast: the ball is thrown sideways off the cloth at the start.
FAST = dict(first_to=2, countdown=0.2, reset_speed=3.0, grace=1.0, restart_delay=30.0)


def run(coro: Awaitable[T], timeout: float = 90.0) -> T:
    async def wrapped() -> T:
        return await asyncio.wait_for(coro, timeout)

    return asyncio.run(wrapped())


@contextlib.asynccontextmanager
async def server(data: Path, *, bots: int = 0, settings: RoomSettings | None = None,
                 **kw: Any) -> AsyncIterator[GameServer]:
    srv = GameServer(data, scenes={"tiny": TINY}, backend="cpu", host="127.0.0.1", port=0,
                     bots=bots, room_settings=settings or RoomSettings(), **kw)
    await srv.start()
    try:
        yield srv
    finally:
        await srv.stop()


async def http_get(srv: GameServer, path: str) -> tuple[int, bytes, dict[str, str]]:
    url = srv.http_url.rstrip("/") + path

    def get() -> tuple[int, bytes, dict[str, str]]:
        try:
            with urllib.request.urlopen(url, timeout=10) as r:
                return r.status, r.read(), dict(r.headers)
        except urllib.error.HTTPError as e:
            with e:
                return e.code, e.read(), dict(e.headers)

    return await asyncio.to_thread(get)


async def http_json(srv: GameServer, path: str) -> Any:
    status, body, _ = await http_get(srv, path)
    assert status == 200, body
    return json.loads(body)


async def until(pred: Callable[[], bool], timeout: float = 10.0, what: str = "") -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while not pred():
        if loop.time() > end:
            raise AssertionError(f"timed out waiting for {what or pred}")
        await asyncio.sleep(0.01)


def local_server(data: Path, *, bots: int = 0, **settings: Any) -> ServerThread:
    """A server with room ``main`` (scene TINY, CPU) on its own thread, not started: what
    ``clothball play --local`` runs. ``settings``: the main room's ``RoomSettings``."""
    settings.setdefault("autoplay", True)
    return ServerThread(data, scenes={TINY.name: TINY}, backend="cpu", bots=bots,
                        room_settings=RoomSettings(**settings))
