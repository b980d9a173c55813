"""``game.net.tap`` and ``game.wire.wsframe.FrameTap``: binary messages taken out of a
websocket stream before websockets reads it, and written at once, with websockets' public
parts only. Checked against websockets' own frames (its ``Frame`` serializes and parses the
reference bytes) and end to end over real sockets; the server's and clients' use of them in
``test_server_fastpaths.py``."""

from __future__ import annotations

import asyncio
import random
from typing import Any

import websockets
from clothball.game.net.tap import TapConnection
from clothball.game.wire.wsframe import (
    OP_BINARY,
    OP_TEXT,
    ZERO_KEY,
    FrameTap,
    binary_frame_header,
    masked_frame,
)
from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.server import ServerConnection, serve
from websockets.frames import Frame, Opcode
from websockets.streams import StreamReader

from tests.server.conftest import run


class _Server(TapConnection, ServerConnection):
    pass


class _Client(TapConnection, ClientConnection):
    pass


def _masked(opcode: Opcode, data: bytes, fin: bool = True) -> bytes:
    return Frame(opcode, data, fin).serialize(mask=True, extensions=[])


def _bare(opcode: Opcode, data: bytes, fin: bool = True) -> bytes:
    return Frame(opcode, data, fin).serialize(mask=False, extensions=[])


def _parse(data: bytes, mask: bool) -> Frame:
    reader = StreamReader()
    reader.feed_data(data)
    parser = Frame.parse(reader.read_exact, mask=mask)
    try:
        next(parser)
    except StopIteration as done:
        assert not reader.buffer  # the whole frame, nothing more
        return done.value
    raise AssertionError("not a whole frame")


def test_frames_written_by_hand_are_what_websockets_reads() -> None:
    """A server's binary frame is byte for byte websockets' own, at every length form (7,
    16 and 64 bits); a client's masked frame (a random key, or the zero key) parses in
    websockets' parser to the same payload."""
    for n in (0, 1, 125, 126, 127, 65535, 65536, 70000):
        data = bytes(range(256)) * (n // 256) + bytes(range(n % 256))
        assert binary_frame_header(n) + data == _bare(Opcode.BINARY, data)
        for key in (None, ZERO_KEY):
            frame = _parse(masked_frame(OP_BINARY, data, key), mask=True)
            assert (frame.opcode, frame.data, frame.fin) == (Opcode.BINARY, data, True)
    text = _parse(masked_frame(OP_TEXT, b'{"type":"ping"}'), mask=True)
    assert (text.opcode, text.data) == (Opcode.TEXT, b'{"type":"ping"}')


def _feed(tap: FrameTap, data: bytes, rng: random.Random) -> bytes:
    out, i = bytearray(), 0
    while i < len(data):
        step = rng.choice((1, 2, 3, 7, 29, 64, 1000, 70000))
        out += tap.feed(data[i:i + step])
        i += step
    return bytes(out)


def test_a_tap_takes_whole_binary_frames_and_passes_every_other_byte() -> None:
    """A client's stream, cut anywhere: each whole binary frame within the size is offered
    unmasked (the payload websockets would read); one taken leaves the stream, one refused
    passes as it came, and every other frame (text, ping, fragmented, larger, unmasked,
    with an RSV bit) passes byte for byte. ``messages`` counts the data messages passed."""
    rng = random.Random(7)
    frames: list[tuple[bytes, bytes | None]] = []  # (frame, payload offered or None)
    for k in range(60):
        payload = bytes([k]) * rng.randrange(0, 300)
        frames.append((_masked(Opcode.BINARY, payload), payload))
        kind = k % 6
        if kind == 0:
            frames.append((_masked(Opcode.TEXT, b'{"type":"x"}' * rng.randrange(1, 30)), None))
        elif kind == 1:
            frames.append((_masked(Opcode.PING, b"hi"), None))
        elif kind == 2:  # a binary message in two fragments: neither is offered
            frames.append((_masked(Opcode.BINARY, b"ab", fin=False), None))
            frames.append((_masked(Opcode.CONT, b"cd"), None))
        elif kind == 3:
            frames.append((_masked(Opcode.BINARY, b"L" * 400), None))  # over max_take
        elif kind == 4:
            frames.append((_bare(Opcode.BINARY, b"bare"), None))  # a client must mask
        else:
            rsv = bytearray(_masked(Opcode.BINARY, b"rsv"))
            rsv[0] |= 0x40
            frames.append((bytes(rsv), None))
    data = b"".join(f for f, _ in frames)
    offered_want = [p for _, p in frames if p is not None]
    for seed in range(6):
        offered: list[bytes] = []

        def take(payload: bytes, offered: list[bytes] = offered) -> bool:
            offered.append(payload)
            return len(offered) % 3 != 0  # every third refused

        tap = FrameTap(take, masked=True, max_take=300)
        out = _feed(tap, data, random.Random(seed))
        assert offered == offered_want
        kept, taken_seen = [], 0
        for f, p in frames:
            if p is None:
                kept.append(f)
                continue
            taken_seen += 1
            if taken_seen % 3 == 0:
                kept.append(f)
        assert out == b"".join(kept)
        # data messages passed: the refused binaries, the texts, the fragmented ones (one
        # message each), the large, the unmasked and the RSV ones
        passed = len(offered_want) // 3 + sum(1 for k in range(60) if k % 6 != 1)
        assert tap.messages == passed


def test_a_tap_lets_the_http_head_pass_first() -> None:
    """From a connection's first byte: the upgrade request (or the 101 answer) passes, and
    frames are followed from the byte after it, however the two are cut; an answer other
    than 101 is no websocket: everything passes and nothing is taken."""
    request = (b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
               b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n")
    answer = (b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
              b"Sec-WebSocket-Accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\n\r\n")
    for head, masked, enc in ((request, True, _masked), (answer, False, _bare)):
        body = b"".join(enc(Opcode.BINARY, bytes([k]) * k) for k in range(1, 30))
        for seed in range(5):
            got: list[bytes] = []
            tap = FrameTap(lambda p, got=got: got.append(p) is None, masked=masked,
                           max_take=1000, head=True)
            out = _feed(tap, head + body, random.Random(seed))
            assert out == head
            assert got == [bytes([k]) * k for k in range(1, 30)]
    refused = b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 4\r\n\r\n"
    tap = FrameTap(lambda p: True, masked=False, max_take=1000, head=True)
    stream = refused + _bare(Opcode.BINARY, b"busy")
    assert _feed(tap, stream, random.Random(1)) == stream and tap.given_up


def test_taken_and_read_messages_arrive_whole_and_in_order() -> None:
    """Over a real socket: binary messages taken by the tap and messages read the usual
    way (text, and binary ones behind a text the reader has not read yet) form one stream
    in the order they were sent; the client's own frames go out by ``send_now``."""

    async def main() -> tuple[list[bytes | str], list[bool]]:
        got: list[bytes | str] = []

        async def handler(ws: ServerConnection) -> None:
            assert isinstance(ws, _Server)
            ws.listen(got.append)
            async for msg in ws:
                ws.message_read()
                got.append(msg)
                await asyncio.sleep(0.05)  # a slow reader: binaries queue behind it

        async with serve(handler, "127.0.0.1", 0, create_connection=_Server,
                         compression=None) as srv:
            port = next(iter(srv.sockets)).getsockname()[1]
            async with connect(f"ws://127.0.0.1:{port}", create_connection=_Client,
                               compression=None) as ws:
                assert isinstance(ws, _Client)
                await asyncio.sleep(0.05)  # the handler has started listening
                direct = [ws.send_now(bytes([i]) * 100) for i in range(50)]
                await ws.send("text")
                for i in range(50, 60):
                    await ws.send(bytes([i]) * 100)
                await ws.send("text 2")
                direct += [ws.send_now(bytes([i]) * 100) for i in range(60, 70)]
                deadline = asyncio.get_running_loop().time() + 20
                while len(got) < 72 and asyncio.get_running_loop().time() < deadline:
                    await asyncio.sleep(0.01)
        return got, direct

    got, direct = run(main(), 60)
    assert all(direct)  # an idle loopback socket takes small messages at once
    want: list[bytes | str] = [bytes([i]) * 100 for i in range(50)]
    want += ["text"] + [bytes([i]) * 100 for i in range(50, 60)] + ["text 2"]
    want += [bytes([i]) * 100 for i in range(60, 70)]
    assert got == want


def test_what_the_tap_passes_websockets_still_checks_and_answers() -> None:
    """Frames the tap does not take reach websockets whole, in order: a ping is answered, a
    binary over the connection's size limit closes it 1009, an unmasked one or one with an
    RSV bit 1002, as without the tap."""

    async def refused(frame: bytes, max_size: int = 2**20) -> tuple[int | None, list[Any]]:
        got: list[Any] = []

        async def handler(ws: ServerConnection) -> None:
            assert isinstance(ws, _Server)
            ws.listen(got.append, 100)
            try:
                async for msg in ws:
                    ws.message_read()
                    got.append(msg)
            except websockets.ConnectionClosed:
                pass

        async with serve(handler, "127.0.0.1", 0, create_connection=_Server,
                         compression=None, max_size=max_size) as srv:
            port = next(iter(srv.sockets)).getsockname()[1]
            async with connect(f"ws://127.0.0.1:{port}", compression=None,
                               create_connection=_Client) as ws:
                await asyncio.sleep(0.05)
                assert isinstance(ws, _Client) and ws.stream is not None
                pong = await asyncio.wait_for(ws.ping(), 5)
                await asyncio.wait_for(pong, 5)  # answered: pings pass the tap
                ws.stream.write(_masked(Opcode.BINARY, b"ok") + frame)
                await asyncio.wait_for(ws.wait_closed(), 5)
                return ws.close_code, got  # the code of the server's close frame

    code, got = run(refused(_masked(Opcode.BINARY, b"x" * 1001), max_size=1000), 30)
    assert code == 1009 and got == [b"ok"]
    code, _ = run(refused(_bare(Opcode.BINARY, b"bare")), 30)
    assert code == 1002
    rsv1 = bytearray(_masked(Opcode.BINARY, b"rsv"))
    rsv1[0] |= 0x40  # no extension negotiated: a reserved bit
    code, _ = run(refused(bytes(rsv1)), 30)
    assert code == 1002


def test_a_client_takes_the_servers_frames_and_a_close_still_closes() -> None:
    """The other side: a client's tap takes the server's unmasked binary frames (a player's
    CORNERs), the same payloads in order, and the server's close frame still ends the
    connection with its code and reason."""

    async def main() -> tuple[list[bytes], int | None, str | None]:
        got: list[bytes] = []

        async def handler(ws: ServerConnection) -> None:
            await ws.recv()
            for i in range(40):
                await ws.send(bytes([i]) * (i * 30))
            await ws.close(4000, "bye")

        async with serve(handler, "127.0.0.1", 0, compression=None) as srv:
            port = next(iter(srv.sockets)).getsockname()[1]
            async with connect(f"ws://127.0.0.1:{port}", create_connection=_Client,
                               compression=None) as ws:
                assert isinstance(ws, _Client)
                ws.listen(got.append)
                await ws.send("go")
                try:
                    async for _ in ws:
                        ws.message_read()
                except websockets.ConnectionClosed:
                    pass
                return got, ws.close_code, ws.close_reason

    got, code, reason = run(main(), 30)
    assert got == [bytes([i]) * (i * 30) for i in range(40)]
    assert (code, reason) == (4000, "bye")
