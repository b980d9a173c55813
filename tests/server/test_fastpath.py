"""``game/net/fastpath.py`` holds every use of websockets' private internals. These tests fail
loudly, naming the internal, when a websockets release changes one; the behaviour of the
fast paths themselves is checked end to end in ``test_server_fastpaths.py``."""

from __future__ import annotations

import asyncio
import inspect

import websockets
from clothball.game.net.fastpath import BinaryHook, try_send_binary
from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.connection import Connection
from websockets.asyncio.messages import Assembler
from websockets.asyncio.server import ServerConnection, serve
from websockets.protocol import OPEN, Protocol

from tests.server.conftest import run


def test_the_internals_the_fast_paths_use_are_there() -> None:
    why = f"websockets {websockets.__version__} changed an internal game/net/fastpath.py uses"
    assert callable(getattr(Connection, "process_event", None)), f"{why}: process_event"
    params = list(inspect.signature(Connection.process_event).parameters)
    assert params == ["self", "event"], f"{why}: process_event{params}"
    assert callable(getattr(Connection, "send_data", None)), f"{why}: send_data"
    assert callable(getattr(Protocol, "send_binary", None)), f"{why}: Protocol.send_binary"

    async def frames() -> bool:
        assembler = Assembler()
        return hasattr(assembler, "frames") and len(assembler.frames) == 0

    assert run(frames()), f"{why}: Assembler.frames"


class _Server(BinaryHook, ServerConnection):
    pass


class _Client(BinaryHook, ClientConnection):
    pass


def test_hooked_and_read_messages_arrive_whole_and_in_order() -> None:
    """Binary messages handed to the hook and messages read the usual way (text, and binary
    ones queued behind it) form one stream in the order they were sent."""

    async def main() -> tuple[list[bytes | str], list[bool]]:
        got: list[bytes | str] = []

        async def handler(ws: ServerConnection) -> None:
            assert isinstance(ws, _Server)
            ws.on_binary = got.append
            async for msg in ws:
                got.append(msg)

        async with serve(handler, "127.0.0.1", 0, create_connection=_Server) as srv:
            port = next(iter(srv.sockets)).getsockname()[1]
            async with connect(f"ws://127.0.0.1:{port}", create_connection=_Client) as ws:
                assert ws.protocol.state is OPEN
                await asyncio.sleep(0.05)  # the handler has set on_binary
                direct = [try_send_binary(ws, bytes([i]) * 100) for i in range(50)]
                await ws.send("text")
                for i in range(50, 60):
                    await ws.send(bytes([i]) * 100)
                deadline = asyncio.get_running_loop().time() + 20
                while len(got) < 61 and asyncio.get_running_loop().time() < deadline:
                    await asyncio.sleep(0.01)
        return got, direct

    got, direct = run(main(), 60)
    assert all(direct)  # an idle loopback socket takes 50 small messages at once
    want: list[bytes | str] = [bytes([i]) * 100 for i in range(50)]
    want += ["text"] + [bytes([i]) * 100 for i in range(50, 60)]
    assert got == want
