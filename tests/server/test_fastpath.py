"""``game/net/fastpath.py`` holds every use of websockets' private internals. These tests fail
loudly, naming the internal, when a websockets release changes one; the behaviour of the
fast paths themselves is checked end to end in ``test_server_fastpaths.py``."""

from __future__ import annotations

import asyncio
import inspect
from typing import Any

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


class _Transport:
    """A socket that takes every write at once and keeps it."""

    def __init__(self) -> None:
        self.written: list[bytes] = []

    def is_closing(self) -> bool:
        return False

    def get_write_buffer_size(self) -> int:
        return 0

    def write(self, data: bytes) -> None:
        self.written.append(bytes(data))


def test_a_server_frame_written_at_once_is_the_one_websockets_serializes() -> None:
    """A server's binary message written by ``try_send_binary`` (its header built there) is
    byte for byte websockets' own frame, at every length form (7, 16 and 64 bits); a client's
    (masked) goes through websockets, as does one sent while the protocol holds unsent
    bytes, which go first."""
    from types import SimpleNamespace

    from websockets.client import ClientProtocol
    from websockets.frames import Frame, Opcode
    from websockets.server import ServerProtocol

    def conn(protocol: Protocol) -> SimpleNamespace:
        protocol.state = OPEN
        transport = _Transport()

        def send_data() -> None:
            for data in protocol.data_to_send():
                transport.write(data)

        return SimpleNamespace(transport=transport, protocol=protocol, send_data=send_data)

    for n in (0, 1, 125, 126, 127, 65535, 65536, 70000):
        data = bytes(range(256)) * (n // 256) + bytes(range(n % 256))
        ws = conn(ServerProtocol())
        assert try_send_binary(ws, data)
        assert b"".join(ws.transport.written) == Frame(Opcode.BINARY, data).serialize(mask=False)
        client = conn(ClientProtocol(websockets.uri.parse_uri("ws://localhost/")))
        assert try_send_binary(client, data)
        frame = b"".join(client.transport.written)
        assert frame[1] & 0x80 and len(frame) == len(Frame(Opcode.BINARY, data)
                                                      .serialize(mask=True))
    ws = conn(ServerProtocol())
    ws.protocol.send_ping(b"p")  # made, not yet written
    assert try_send_binary(ws, b"after")
    want = Frame(Opcode.PING, b"p").serialize(mask=False) + \
        Frame(Opcode.BINARY, b"after").serialize(mask=False)
    assert b"".join(ws.transport.written) == want


def _masked(opcode: Any, data: bytes, fin: bool = True) -> bytes:
    from websockets.frames import Frame

    return Frame(opcode, data, fin).serialize(mask=True)


def test_frames_parsed_in_the_fast_path_are_websockets_own_and_the_rest_goes_to_it() -> None:
    """Bytes fed to a hooked server connection as a socket would: whole binary frames read
    between frames are handed over without websockets' parser (it sees none of them), the
    same payloads in the same order; a frame split over two reads, a text, a ping and the
    frames after them go through websockets (the ping answered); a frame over the size
    limit, an unmasked one and one with an RSV bit still close the connection as websockets
    does (1009, 1002, 1002)."""
    from clothball.game.net.fastpath import between_frames
    from websockets.frames import Opcode

    async def main() -> dict[str, Any]:
        out: dict[str, Any] = {"got": [], "closed": []}
        conns: list[Any] = []

        async def handler(ws: ServerConnection) -> None:
            ws.on_binary = out["got"].append
            conns.append(ws)
            try:
                async for msg in ws:
                    out["got"].append(msg)
            except websockets.ConnectionClosed:
                pass
            out["closed"].append(ws.protocol.close_sent.code if ws.protocol.close_sent else None)

        async with serve(handler, "127.0.0.1", 0, create_connection=_Server,
                         max_size=1000, compression=None) as srv:  # as the server's
            port = next(iter(srv.sockets)).getsockname()[1]
            async with connect(f"ws://127.0.0.1:{port}", compression=None) as client:
                while not conns:
                    await asyncio.sleep(0.01)
                ws = conns[0]
                parsed: list[bytes] = []
                feed = ws.protocol.receive_data

                def counting(data: bytes) -> None:
                    parsed.append(bytes(data))
                    feed(data)

                ws.protocol.receive_data = counting
                assert between_frames(ws.protocol)
                # 0 to 280 bytes: lengths of 7 and of 16 bits
                frames = [bytes([i]) * (i * 40) for i in range(8)]
                ws.data_received(b"".join(_masked(Opcode.BINARY, f) for f in frames))
                out["fast"] = (list(out["got"]), list(parsed))
                one = _masked(Opcode.BINARY, b"split" * 30)
                ws.data_received(one[:7])
                ws.data_received(one[7:] + _masked(Opcode.BINARY, b"next"))
                ws.data_received(_masked(Opcode.PING, b"hi") + _masked(Opcode.BINARY, b"after"))
                pong = await asyncio.wait_for(client.ping(), 5)
                await asyncio.wait_for(pong, 5)  # the server's pongs, ours first, have come
                ws.data_received(_masked(Opcode.TEXT, b"text") + _masked(Opcode.BINARY, b"z"))
                deadline = asyncio.get_running_loop().time() + 5
                while len(out["got"]) < 13 and asyncio.get_running_loop().time() < deadline:
                    await asyncio.sleep(0.01)
                out["slow"] = list(parsed)
                assert between_frames(ws.protocol)
                ws.data_received(_masked(Opcode.BINARY, b"x" * 1001))
                while not out["closed"]:
                    await asyncio.sleep(0.01)
        return out

    out = run(main(), 60)
    frames = [bytes([i]) * (i * 40) for i in range(8)]
    got, parsed = out["fast"]
    assert got == frames and parsed == []  # websockets' parser saw none of them
    assert out["got"][8:] == [b"split" * 30, b"next", b"after", "text", b"z"]
    # websockets parsed the split frame's two reads, our ping's, the client's ping (a read
    # of the real socket) and the text's: five
    assert len(out["slow"]) == 5
    assert out["closed"] == [1009]

    async def refused(frame: bytes) -> int | None:
        codes: list[int | None] = []

        async def handler(ws: ServerConnection) -> None:
            ws.on_binary = lambda data: None
            await asyncio.sleep(0.05)
            ws.data_received(_masked(Opcode.BINARY, b"ok") + frame)
            try:
                async for _ in ws:
                    pass
            except websockets.ConnectionClosed:
                pass
            codes.append(ws.protocol.close_sent.code if ws.protocol.close_sent else None)

        async with serve(handler, "127.0.0.1", 0, create_connection=_Server,
                         compression=None) as srv:
            port = next(iter(srv.sockets)).getsockname()[1]
            async with connect(f"ws://127.0.0.1:{port}", compression=None):
                while not codes:
                    await asyncio.sleep(0.01)
        return codes[0]

    from websockets.frames import Frame

    assert run(refused(Frame(Opcode.BINARY, b"bare").serialize(mask=False)), 30) == 1002
    rsv1 = bytearray(_masked(Opcode.BINARY, b"rsv"))
    rsv1[0] |= 0x40  # no extension negotiated: a reserved bit
    assert run(refused(bytes(rsv1)), 30) == 1002


def test_a_client_takes_the_servers_unmasked_frames_in_the_fast_path() -> None:
    """The other side: a hooked client connection (a player's CORNERs) parses the server's
    unmasked binary frames itself, the same payloads in order, websockets' parser seeing
    none; a masked frame from a server is websockets' to refuse (1002)."""
    from websockets.frames import Frame, Opcode

    async def main() -> tuple[list[bytes], list[bytes], int | None]:
        got: list[bytes] = []
        parsed: list[bytes] = []

        async def handler(ws: ServerConnection) -> None:
            await ws.wait_closed()

        async with serve(handler, "127.0.0.1", 0, compression=None) as srv:
            port = next(iter(srv.sockets)).getsockname()[1]
            async with connect(f"ws://127.0.0.1:{port}", create_connection=_Client,
                               compression=None) as ws:
                ws.on_binary = got.append
                feed = ws.protocol.receive_data

                def counting(data: bytes) -> None:
                    parsed.append(bytes(data))
                    feed(data)

                ws.protocol.receive_data = counting
                frames = [bytes([i]) * (i * 30) for i in range(6)]
                ws.data_received(b"".join(Frame(Opcode.BINARY, f).serialize(mask=False)
                                          for f in frames))
                fast = list(parsed)
                ws.data_received(Frame(Opcode.BINARY, b"masked").serialize(mask=True))
                try:
                    await asyncio.wait_for(ws.recv(), 5)
                except websockets.ConnectionClosed:
                    pass
                code = ws.protocol.close_sent.code if ws.protocol.close_sent else None
        assert got == frames
        return got, fast, code

    _, fast, code = run(main(), 30)
    assert fast == [] and code == 1002
