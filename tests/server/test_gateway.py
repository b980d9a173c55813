"""The gateway's parts. Its pump's reading of a server's stream (``_native.ServerFollow``,
native/net/follow.hpp):
after any prefix of an HTTP 101 answer and a run of server frames made by websockets' own
encoder (the reference), cut into chunks anywhere, it says a close frame may be written
exactly when the prefix ends between two complete messages, and never after the server's
close frame or in an HTTP answer that is not an upgrade. The PROXY line
(``server.shared.proxyline``): the protocol's own examples, and an engine behind a real
gateway that applies its per-address limit to the client's address."""

from __future__ import annotations

import asyncio
import json
import random
import subprocess
import sys
import urllib.error
import urllib.request

import pytest
from clothball import _native
from clothball.game.wire import protocol as P
from clothball.server.gateway.frames import close_frame, text_frame
from clothball.server.limits import Limits
from clothball.server.shared import proxyline
from hypothesis import given, settings
from hypothesis import strategies as st
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed
from websockets.frames import Close, Frame, Opcode

from tests.server import workers
from tests.server.conformance_client import HELLO
from tests.server.conftest import run, server, until

HEAD = b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\r\n"
SIZES = (0, 1, 125, 126, 127, 300, 65535, 65536, 70000)  # each header length form


def stream(rng: random.Random, n: int) -> tuple[bytes, set[int]]:
    """``n`` messages (some in several frames) as bytes after HEAD, and the offsets (from
    the stream's start) that lie between two messages."""
    out, ends = bytearray(HEAD), {len(HEAD)}
    for _ in range(n):
        parts = rng.choice((1, 1, 2, 3))
        for k in range(parts):
            op = (Opcode.BINARY if rng.random() < 0.5 else Opcode.TEXT) if k == 0 \
                else Opcode.CONT
            data = bytes(rng.randrange(256) for _ in range(rng.choice(SIZES) % 2000)) \
                if rng.random() < 0.8 else b"x" * rng.choice(SIZES)
            if op is Opcode.TEXT:
                data = data.hex().encode()[: len(data)]
            out += Frame(op, data, fin=k == parts - 1).serialize(mask=False,
                                                                 extensions=[])
            if rng.random() < 0.2 and k < parts - 1:  # a ping between fragments
                out += Frame(Opcode.PING, b"p").serialize(mask=False, extensions=[])
        ends.add(len(out))
    return bytes(out), ends


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32), st.integers(1, 12))
def test_between_messages_exactly_at_message_boundaries(seed: int, n: int) -> None:
    rng = random.Random(seed)
    data, ends = stream(rng, n)
    frames, at = _native.ServerFollow(), 0
    while at < len(data):
        step = rng.choice((1, 2, 3, 7, 64, 1000, 70000))
        frames.feed(data[at:at + step])
        at = min(len(data), at + step)
        assert frames.between_messages() == (at in ends), at


def lane_payload(seat: int | None) -> bytes:
    from clothball.server.shared.lanes import LaneSpec, lane_message
    lane = None if seat is None else LaneSpec("main", 1, 0, seat, 7, (0, 0, 0),
                                          (1, 1, 1), 0.008, 500.0, 50.0, 9, 14400)
    return P.encode_json(lane_message(lane)).encode()


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32), st.integers(1, 12))
def test_lane_messages_are_taken_out_and_every_other_byte_passes(seed: int, n: int) -> None:
    """The engine's lane messages (server.shared.lanes), put between the messages of a
    stream, reach ``on_lane`` whole and in order and never the client; the rest of the
    stream passes byte for byte, however it is cut."""
    rng = random.Random(seed)
    data, ends = stream(rng, n)
    lanes = [lane_payload(rng.choice((None, 0, 3))) for _ in range(3)]
    at = sorted(rng.sample(sorted(ends), min(3, len(ends))))
    with_lanes, prev = bytearray(), 0
    for cut, lane in zip(at, lanes, strict=False):
        with_lanes += data[prev:cut] + Frame(Opcode.TEXT, lane).serialize(mask=False,
                                                                            extensions=[])
        prev = cut
    with_lanes += data[prev:]
    seen: list[bytes] = []
    frames, out, i = _native.ServerFollow(), bytearray(), 0
    while i < len(with_lanes):
        step = rng.choice((1, 2, 3, 7, 64, 1000, 70000))
        out += frames.feed(with_lanes[i:i + step], seen.append)
        i += step
    assert bytes(out) == data
    assert seen == lanes[:len(at)]


def test_a_clients_hips_are_offered_whole_and_the_rest_passes() -> None:
    """A client's stream (masked frames, as websockets' client writes them): each whole
    HIP-sized binary frame is offered unmasked; one taken is dropped, one refused passes
    as it came, and every other frame passes byte for byte, however the stream is cut."""
    rng = random.Random(5)
    hips = [P.encode_hip((0.1 * k, 1.0, -0.2), k, 0.5 * k) for k in range(1, 41)]
    frames = []  # a HIP, then a text message, each time
    for h in hips:
        frames.append(Frame(Opcode.BINARY, h).serialize(mask=True, extensions=[]))
        frames.append(Frame(Opcode.TEXT, b'{"type":"ping"}' * rng.randrange(1, 20)).serialize(
            mask=True, extensions=[]))
    data = b"".join(frames)
    # every fifth HIP refused: it passes as it came, as do the text messages
    passed = b"".join(f for k, f in enumerate(frames) if k % 2 == 1 or (k // 2) % 5 == 4)
    for cut in (1, 2, 3, 7, 29, 64, 1000):
        offered: list[bytes] = []

        def take(payload: bytes, offered: list[bytes] = offered) -> bool:
            offered.append(payload)
            return (len(offered) - 1) % 5 != 4

        cf, out, i = _native.ClientTap(P.HIP_SIZE), bytearray(), 0
        while i < len(data):
            out += cf.feed(data[i:i + cut], take)
            i += cut
        assert offered == hips, cut
        assert bytes(out) == passed, cut


def test_after_the_close_frame_and_for_plain_http_never() -> None:
    f = _native.ServerFollow()
    f.feed(HEAD + Frame(Opcode.CLOSE, Close(1000, "bye").serialize()).serialize(
        mask=False, extensions=[]))
    assert f.closed and not f.between_messages()
    g = _native.ServerFollow()
    g.feed(b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\n{}")
    assert g.given_up and not g.between_messages()


def test_the_close_frame_is_what_websockets_reads() -> None:
    from websockets.streams import StreamReader

    reader = StreamReader()
    reader.feed_data(close_frame(1011, "the host's engine stopped"))
    parser = Frame.parse(reader.read_exact, mask=False)
    try:
        next(parser)
    except StopIteration as done:
        frame = done.value
    assert frame.opcode is Opcode.CLOSE
    assert Close.parse(frame.data) == Close(1011, "the host's engine stopped")


def _text(msg: dict) -> bytes:
    """``msg`` as the engine sends it: its encoder, websockets' framing."""
    return Frame(Opcode.TEXT, P.encode_json(msg).encode()).serialize(mask=False,
                                                                     extensions=[])


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32))
def test_the_room_a_client_is_in_as_the_engine_said(seed: int) -> None:
    """Followed through any split of the stream: a ``joined`` (however long: its geometry
    and state follow the room) puts the client in its room, binary messages' headers and
    events give the room's frame and time, and ``left`` or an error ``room_stopped`` take
    it out; other errors do not."""
    rng = random.Random(seed)
    # The engine's room ids: "main", "main-" and 6 hex digits, token_urlsafe(6); and any.
    room = rng.choice(["main", "main-0a1b2c", "aB3-_x9Q", 'r"q\\x', "room-" + "é" * 20])
    joined = {"type": "joined", "room": room, "role": "player", "seat": 2,
              "geometry": {"n": 48, "pad": "x" * rng.choice((10, 200, 70000))}}
    mesh = P.HEADER.pack(3, 1, 0, 7, 0.25) + bytes(rng.randrange(256) for _ in range(300))
    steps = [
        (_text({"type": "welcome", "rooms": [{"id": "other"}]}), None, -1),
        (_text(joined), room, -1),
        (Frame(Opcode.BINARY, mesh).serialize(mask=False, extensions=[]), room, 7),
        (_text({"type": "event", "event": "score", "room": room, "frame": 12345,
                "time": 12.5, "round": 1}), room, 12345),
        (_text(P.error_message("rate_limited", "slow down")), room, 12345),
        (_text({"type": "left", "room": room, "re": 3}), None, 12345),
        (_text(joined), room, -1),
        (Frame(Opcode.BINARY, P.HEADER.pack(2, 1, 0, 2**32 - 1, 3.0) + bytes(88)).serialize(
            mask=False, extensions=[]), room, 2**32 - 1),
        (Frame(Opcode.BINARY, P.HEADER.pack(2, 1, 0, 1, 3.5) + bytes(88)).serialize(
            mask=False, extensions=[]), room, 2**32 + 1),  # seq wrapped: the frame goes on
        (Frame(Opcode.BINARY, P.HEADER.pack(2, 1, 0, 2**32 - 2, 9.0) + bytes(88)).serialize(
            mask=False, extensions=[]), room, 2**32 + 1),  # an older frame's: not taken
        (_text(P.error_message("room_stopped", "room stopped: non-finite")), None, 2**32 + 1),
    ]
    f = _native.ServerFollow()
    data = HEAD + b"".join(b for b, _, _ in steps)
    at, ends, end = 0, [], len(HEAD)
    for b, r, fr in steps:  # each message's end in the stream, and what holds there
        end += len(b)
        ends.append((end, r, fr))
    expect = iter(ends)
    end, r, fr = next(expect)
    while at < len(data):
        step = min(rng.choice((1, 2, 5, 64, 1000, 70000)), end - at)
        f.feed(data[at:at + step])
        at += step
        if at == end:
            # (the room as the engine's JSON wrote it, quoted)
            room_now = None if f.room is None else json.loads(f.room)
            assert (room_now, f.frame) == (r, fr), (at, f.room, f.frame)
            if fr == 12345:
                assert f.time == 12.5
            end, r, fr = next(expect, (len(data) + 1, None, 0))


def test_the_gateways_own_messages_are_what_websockets_reads() -> None:
    from websockets.streams import StreamReader

    msg = {"type": "event", "event": "room_stopped", "room": "x" * 200, "frame": 1,
           "time": 0.5, "reason": "gone"}
    reader = StreamReader()
    reader.feed_data(text_frame(msg))
    parser = Frame.parse(reader.read_exact, mask=False)
    try:
        next(parser)
    except StopIteration as done:
        frame = done.value
    assert frame.opcode is Opcode.TEXT and frame.fin
    assert P.decode_json(frame.data.decode()) == msg


def test_proxy_lines_as_the_protocol_writes_them() -> None:
    # The examples of the PROXY protocol's specification (version 1, section 2.1).
    assert proxyline.encode(("192.168.0.1", 56324), ("192.168.0.11", 443)) == \
        b"PROXY TCP4 192.168.0.1 192.168.0.11 56324 443\r\n"
    assert proxyline.decode(b"PROXY TCP4 192.168.0.1 192.168.0.11 56324 443\r\n") == \
        ("192.168.0.1", 56324)
    assert proxyline.decode(b"PROXY TCP6 ::1 ::1 5000 8765\r\n") == ("::1", 5000)
    assert proxyline.encode(("::1", 5000, 0, 0), ("::1", 8765, 0, 0)) == \
        b"PROXY TCP6 ::1 ::1 5000 8765\r\n"
    assert proxyline.decode(b"PROXY UNKNOWN\r\n") is None
    assert proxyline.encode(None, None) == b"PROXY UNKNOWN\r\n"
    # A gateway that serves lanes says so with one more word; the address is the same.
    line = proxyline.encode(("192.168.0.1", 56324), ("192.168.0.11", 443), lanes=True)
    assert line == b"PROXY TCP4 192.168.0.1 192.168.0.11 56324 443 LANES\r\n"
    assert proxyline.decode(line) == ("192.168.0.1", 56324) and proxyline.lanes(line)
    assert not proxyline.lanes(b"PROXY TCP4 192.168.0.1 192.168.0.11 56324 443\r\n")
    assert proxyline.decode(proxyline.encode(None, None, lanes=True)) is None
    # the port the client connected to (the engine tells its own port's connections by it)
    assert proxyline.local_port(line) == 443
    assert proxyline.local_port(b"PROXY TCP6 ::1 ::1 5000 8765\r\n") == 8765
    assert proxyline.local_port(b"PROXY UNKNOWN LANES\r\n") is None
    for bad in (b"GET / HTTP/1.1\r\n", b"PROXY TCP4 1.2.3.4\r\n",
                b"PROXY TCP4 x 1.2.3.4 1 2\r\n", b"PROXY TCP4 1.2.3.4 1.2.3.4 1 2",
                b"PROXY " + b"9" * 200 + b"\r\n"):
        with pytest.raises(proxyline.BadLine):
            proxyline.decode(bad)


def test_an_engine_behind_a_gateway_limits_the_clients_address(tmp_path) -> None:
    """conns_per_address=1 through a real gateway: a second connection from 127.0.0.1 is
    refused naming that address (the engine read it from the gateway's PROXY line; the
    gateway's own end of the Unix socket has none)."""
    async def main() -> None:
        async with server(tmp_path, limits=Limits(conns_per_address=1)) as srv:
            assert srv.engine_socket is not None
            url = f"ws://127.0.0.1:{workers.public_port(srv)}/ws"
            async with connect(url) as first:
                await first.send(json.dumps(HELLO))
                assert json.loads(await first.recv())["type"] == "welcome"
                async with connect(url) as second:
                    with pytest.raises(ConnectionClosed):
                        await second.recv()
                    assert second.close_code == 1008
                    assert "too many connections from 127.0.0.1" in second.close_reason

    with workers.using(2):
        run(main())


def test_a_gateway_without_its_engine_answers_503_saying_so(tmp_path) -> None:
    from clothball.server.gateway.relay import RETRY_AFTER_S, Gateway
    from clothball.server.hostproc import free_port

    async def main() -> None:
        gw = Gateway("127.0.0.1", free_port(), tmp_path / "no-engine.sock")
        await gw.start()
        try:
            def get() -> urllib.error.HTTPError:
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{gw.port}/api/rooms",
                                                timeout=10):
                        pass
                except urllib.error.HTTPError as e:
                    return e
                raise AssertionError("answered 2xx with no engine")

            with await asyncio.to_thread(get) as e:  # (its response closed after)
                assert e.code == 503 and e.headers["Retry-After"] == str(RETRY_AFTER_S)
                assert "engine is restarting" in json.loads(e.read())["error"]
        finally:
            await gw.stop()

    run(main())


def test_the_control_socket_gives_a_gateway_its_frame_wake_up_and_arms_it(tmp_path) -> None:
    """The engine's control socket (``server.lanes.control``) as a gateway speaks to it
    (``server.shared.lanes``): ``WAKE`` passes an eventfd, the same one the engine hands
    its frame loops on ``ARM`` and takes back on ``DISARM`` and when the gateway's
    connection ends (then closing its own descriptor); a line that is none of these is
    logged and changes nothing."""
    import os
    import socket

    from clothball.server.lanes.control import GatewayControl
    from clothball.server.shared import lanes

    async def main() -> None:
        calls: list[tuple[int, bool]] = []
        stats = {"messages_in": 0, "messages_out": 0, "lane_messages_in": 0,
                 "lane_messages_out": 0}
        ctl = GatewayControl(tmp_path / "e.sock.ctl", lambda: [], stats,
                             lambda fd, on: calls.append((fd, on)))
        await ctl.start()
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            s.settimeout(5.0)
            await asyncio.to_thread(s.connect, str(ctl.path))
            mine = await asyncio.to_thread(lanes.receive_wake, s)
            assert calls == []  # not armed by being asked for
            s.sendall(lanes.ARM + b"not a line\n")
            await until(lambda: calls, 5, "armed")
            (theirs, on), = calls
            assert on and theirs != mine
            os.eventfd_write(theirs, 3)  # what a frame loop writes reaches the gateway
            assert os.eventfd_read(mine) == 3
            s.sendall(lanes.DISARM)
            await until(lambda: len(calls) == 2, 5, "disarmed")
            assert calls[1] == (theirs, False)
            assert stats["messages_in"] == 0
            s.close()
            await until(lambda: len(calls) == 3, 5, "taken back as the gateway leaves")
            assert calls[2] == (theirs, False)
            # The engine's descriptor is closed: of this process's, only the gateway's
            # refers to that eventfd (marked with a count no other has).
            os.eventfd_write(mine, 0x5EED)

            def marked(fd: str) -> bool:
                try:
                    with open(f"/proc/self/fdinfo/{fd}") as f:
                        return "eventfd-count:5eed" in "".join(f.read().split()).lower()
                except OSError:
                    return False
            assert [int(fd) for fd in os.listdir("/proc/self/fdinfo") if marked(fd)] == [mine]
            os.close(mine)
        finally:
            s.close()
            await ctl.stop()

    run(main())


def test_the_pumps_tick_from_the_environment_is_checked(monkeypatch) -> None:
    from clothball.server.gateway.lanes import COALESCE_ENV, pump_coalesce_s
    monkeypatch.delenv(COALESCE_ENV, raising=False)
    assert pump_coalesce_s() is None
    monkeypatch.setenv(COALESCE_ENV, "250")
    assert pump_coalesce_s() == pytest.approx(250e-6)
    for bad in ("-1", "nan", "1e9", "fast"):
        monkeypatch.setenv(COALESCE_ENV, bad)
        with pytest.raises(ValueError, match=f"{COALESCE_ENV}=.*microseconds from 0 to 10000"):
            pump_coalesce_s()
    with pytest.raises(ValueError, match="0 to 0.01 s"):
        _native.Pump(0.5)


@pytest.mark.parametrize("args, says", [
    (["--slow-drop-s", "nan"], "slow_drop_s"), (["--slow-drop-s", "0"], "slow_drop_s"),
    (["--send-buffer", "0"], "send buffer"), (["--send-buffer", "-5"], "send buffer")])
def test_a_gateway_given_a_bad_slow_client_limit_says_so_and_exits_1(tmp_path, args,
                                                                      says) -> None:
    """What ``clothball host`` gives a gateway (its Limits, checked there) is checked again
    where it is used: one JSON line naming it, exit 1, no traceback."""
    proc = subprocess.run(
        [sys.executable, "-m", "clothball.server.gateway", "--host", "127.0.0.1", "--port",
         str(workers.free_port()), "--engine-socket", str(tmp_path / "engine.sock"), *args],
        capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1, proc
    said = json.loads(proc.stdout.splitlines()[0])
    assert says in said["error"] and "Traceback" not in proc.stderr, (said, proc.stderr)
