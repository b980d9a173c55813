"""The gateway's pump (``_native.Pump``, native/net/pump.hpp) on socket pairs, each side
played by the test: the bytes both ways as they were sent (the PROXY line first), the
engine's lane messages taken out of its stream and told, half-closes passed on, the
engine's end told with where the stream stood, the gateway's tail written before the end,
and backpressure: a client that stops reading stops the engine's side being read, and an
engine that hangs up meanwhile is read to its end once the client reads again. The lanes'
HIPs and CORNERs through a real host are ``test_workers.py``'s."""

from __future__ import annotations

import contextlib
import json
import socket
import struct
import time
from collections.abc import Iterator

import pytest
from clothball import _native
from clothball.game.wire import protocol as P
from clothball.server.gateway.relay import SEND_BUFFER
from clothball.server.limits import Limits
from clothball.server.shared.lanes import LaneSpec, lane_message
from websockets.frames import Frame, Opcode

HEAD = b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\r\n"
WAIT_S = 10.0


def text(payload: bytes) -> bytes:
    return Frame(Opcode.TEXT, payload).serialize(mask=False, extensions=[])


def recv_exactly(s: socket.socket, n: int) -> bytes:
    out = bytearray()
    s.settimeout(WAIT_S)
    while len(out) < n:
        chunk = s.recv(n - len(out))
        assert chunk, f"ended after {len(out)} of {n} bytes"
        out += chunk
    return bytes(out)


def recv_to_end(s: socket.socket) -> bytes:
    out = bytearray()
    s.settimeout(WAIT_S)
    while chunk := s.recv(1 << 16):
        out += chunk
    return bytes(out)


def events(pump: _native.Pump, want: str, within_s: float = WAIT_S) -> list[tuple]:
    """The pump's events up to the first of kind ``want`` (which is last)."""
    seen: list[tuple] = []
    end = time.monotonic() + within_s
    while time.monotonic() < end:
        for ev in pump.take_events():
            seen.append(ev)
            if ev[0] == want:
                return seen
        time.sleep(0.005)
    raise AssertionError(f"no {want!r} event within {within_s} s: {seen}")


@contextlib.contextmanager
def relayed(pump: _native.Pump, sndbuf: int | None = None
            ) -> Iterator[tuple[_native.Pump, int, socket.socket, socket.socket]]:
    """``pump`` relaying one connection: (pump, conn, the client's end, the engine's end);
    ``sndbuf``: the kernel's send buffer of the pump's socket to the client."""
    client, c_pump = socket.socketpair()
    engine, e_pump = socket.socketpair()
    if sndbuf is not None:
        c_pump.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, sndbuf)
    c_pump.setblocking(False)
    e_pump.setblocking(False)
    conn = pump.add(c_pump.detach(), e_pump.detach(), b"PROXY TCP4 1.2.3.4 5.6.7.8 1 2\r\n",
                    False)
    try:
        yield pump, conn, client, engine
    finally:
        pump.stop()
        client.close()
        engine.close()


@pytest.fixture
def relay():
    """A pump relaying one connection: (pump, conn, the client's end, the engine's end)."""
    with relayed(_native.Pump()) as r:
        yield r


def test_bytes_pass_both_ways_and_lane_messages_are_taken_out(relay) -> None:
    pump, conn, client, engine = relay
    request = b"GET /ws HTTP/1.1\r\nHost: x\r\n\r\n"
    client.sendall(request)
    proxy = b"PROXY TCP4 1.2.3.4 5.6.7.8 1 2\r\n"
    assert recv_exactly(engine, len(proxy) + len(request)) == proxy + request
    lane = LaneSpec("main", 1, 0, 2, 7, (0, 0, 0), (1, 1, 1), 0.008, 500.0, 50.0, None, 0)
    lane_msg = P.encode_json(lane_message(lane)).encode()
    joined = text(P.encode_json({"type": "joined", "room": "main"}).encode())
    engine.sendall(HEAD + joined + text(lane_msg) + text(b'{"type":"ok"}'))
    want = HEAD + joined + text(b'{"type":"ok"}')
    assert recv_exactly(client, len(want)) == want
    (ev,) = [e for e in events(pump, "lane") if e[0] == "lane"]
    assert ev == ("lane", conn, lane_msg)
    assert pump.connections == 1


def test_a_half_close_passes_on_and_the_engines_end_is_told(relay) -> None:
    pump, conn, client, engine = relay
    engine.sendall(HEAD + text(P.encode_json({"type": "joined", "room": "r\"1"}).encode()))
    recv_exactly(client, len(HEAD))
    client.shutdown(socket.SHUT_WR)
    got = recv_to_end(engine)  # the client's end reached the engine, after the PROXY line
    assert got.startswith(b"PROXY ")
    engine.close()
    ended = events(pump, "ended")[-1]
    # between two messages, in the room (as the engine's JSON wrote it), no frame yet
    assert ended[:4] == ("ended", conn, True, json.dumps('r"1'))
    assert ended[4] == -1
    pump.finish(conn, b"the gateway's tail")
    rest = recv_to_end(client)
    assert rest.endswith(b"the gateway's tail")
    assert events(pump, "closed")[-1] == ("closed", conn)
    assert pump.connections == 0


def test_a_client_that_stops_reading_holds_the_engine_back_until_it_reads(relay) -> None:
    """Past 256 KiB unsent to the client the engine's side is not read (its writes wait);
    an engine that hangs up meanwhile is read to its last byte once the client reads, and
    only then is its end told."""
    pump, conn, client, engine = relay
    client.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    engine.setblocking(False)
    engine.sendall(HEAD)
    sent = bytearray(HEAD)
    blob = bytes(range(256)) * 256  # 64 KiB
    end = time.monotonic() + WAIT_S
    stalled_at = None
    while time.monotonic() < end:  # write until the engine's writes stop being taken
        try:
            n = engine.send(blob)
            sent += blob[:n]
            stalled_at = None
        except BlockingIOError:
            if stalled_at is None:
                stalled_at = time.monotonic()
            elif time.monotonic() - stalled_at > 0.5:
                break
            time.sleep(0.01)
    assert len(sent) > (1 << 18), "the engine's side was never held back"
    assert not [e for e in pump.take_events() if e[0] == "ended"]
    engine.close()  # hangs up while the pump holds its side back
    time.sleep(0.2)
    assert not [e for e in pump.take_events() if e[0] == "ended"]  # its bytes still wait
    got = recv_exactly(client, len(sent))
    assert got == bytes(sent)
    assert events(pump, "ended")[-1][:2] == ("ended", conn)


def test_a_client_that_resets_ends_both_sides(relay) -> None:
    pump, conn, client, engine = relay
    client.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
    client.close()
    assert events(pump, "closed")[-1] == ("closed", conn)
    assert recv_to_end(engine).startswith(b"PROXY ")  # then its end


# --- too slow: a websocket client behind for longer than slow_drop_s is dropped -----------------

SLOW_S = 0.5  # the pumps' slow_drop_s below
MARGIN_S = 1.0  # the most a drop may come after slow_drop_s (a loaded machine's)


def send_until_held(engine: socket.socket, frames: Iterator[bytes], most: int) -> bytes:
    """The engine writes ``frames`` until ``most`` bytes went or its writes have not been
    taken for 0.1 s; what went."""
    engine.setblocking(False)
    sent = bytearray()
    held_since = None
    for f in frames:
        while f and len(sent) < most:
            try:
                n = engine.send(f)
            except BlockingIOError:
                if held_since is None:
                    held_since = time.monotonic()
                elif time.monotonic() - held_since > 0.1:
                    break
                time.sleep(0.005)
                continue
            held_since = None
            sent += f[:n]
            f = f[n:]
        if f:
            break
    engine.setblocking(True)
    return bytes(sent)


def engine_end_after(engine: socket.socket, t0: float) -> float:
    """Reads the engine's side to its end (the PROXY line first): when that came, from
    ``t0``."""
    assert recv_to_end(engine).startswith(b"PROXY ")
    return time.monotonic() - t0


def close_of(data: bytes) -> tuple[int, bytes]:
    """The code and reason of the server's close frame that is all of ``data``."""
    assert data[0] == 0x88, data[:16]
    n = data[1]
    assert n < 126 and len(data) == 2 + n, data
    return struct.unpack(">H", data[2:4])[0], data[4:]


def test_a_websocket_client_that_stops_reading_is_dropped_after_slow_drop_s() -> None:
    """Past 64 KiB unsent for slow_drop_s: the engine's side closed (it sees the client go),
    and the client, reading again, gets all that was queued for it, then the close frame
    1008 ``too slow: ...`` and its end."""
    with relayed(_native.Pump(slow_drop_s=SLOW_S), sndbuf=4096) as (pump, conn, client,
                                                                    engine):
        msg = text(b'{"type":"event","pad":"' + b"x" * 1000 + b'"}')
        t0 = time.monotonic()
        sent = send_until_held(engine, iter([HEAD] + [msg] * 200), 200 * 1024)
        assert len(sent) > 128 * 1024  # well past the 64 KiB at which it is behind
        took = engine_end_after(engine, t0)
        assert SLOW_S <= took < SLOW_S + MARGIN_S, took
        assert pump.slow_drops == 1
        got = recv_to_end(client)
        assert got.startswith(sent)
        code, reason = close_of(got[len(sent):])
        assert code == 1008 and reason.startswith(b"too slow: "), reason
        assert events(pump, "closed")[-1] == ("closed", conn)
        assert pump.connections == 0


def test_a_dropped_client_that_does_not_read_its_close_is_cut_2_s_later() -> None:
    with relayed(_native.Pump(slow_drop_s=SLOW_S), sndbuf=4096) as (pump, conn, client,
                                                                    engine):
        msg = text(b'{"type":"event","pad":"' + b"x" * 1000 + b'"}')
        t0 = time.monotonic()
        sent = send_until_held(engine, iter([HEAD] + [msg] * 200), 200 * 1024)
        assert len(sent) > 128 * 1024
        engine_end_after(engine, t0)
        dropped = time.monotonic()
        assert pump.connections == 1  # its close frame waits for it
        assert events(pump, "closed")[-1] == ("closed", conn)
        cut_after = time.monotonic() - dropped
        assert 1.5 < cut_after < 2.0 + MARGIN_S, cut_after
        assert pump.connections == 0


def test_a_client_behind_within_a_message_is_cut() -> None:
    """Dropped in the middle of one of the engine's messages, where no close frame can
    follow: the client gets a part of that message and its end, the engine its end."""
    with relayed(_native.Pump(slow_drop_s=SLOW_S), sndbuf=4096) as (pump, conn, client,
                                                                    engine):
        big = Frame(Opcode.BINARY, bytes(1 << 20)).serialize(mask=False, extensions=[])
        chunks = (big[i:i + 4096] for i in range(0, len(big), 4096))
        t0 = time.monotonic()
        sent = send_until_held(engine, iter([HEAD, *chunks]), 200 * 1024)
        assert 128 * 1024 < len(sent) < len(HEAD) + len(big)
        took = engine_end_after(engine, t0)
        assert SLOW_S <= took < SLOW_S + MARGIN_S, took
        # cut with its engine's side (not 2 s later)
        assert events(pump, "closed", within_s=0.5)[-1] == ("closed", conn)
        got = recv_to_end(client)
        assert len(got) <= len(sent) and sent.startswith(got)  # no frame of the pump's
        assert pump.slow_drops == 1


def test_a_client_that_takes_nothing_is_dropped_with_little_unsent() -> None:
    """Less than 64 KiB unsent, but none of it taken for slow_drop_s: dropped too."""
    with relayed(_native.Pump(slow_drop_s=SLOW_S), sndbuf=4096) as (pump, conn, client,
                                                                    engine):
        msg = text(b'{"type":"event","pad":"' + b"x" * 200 + b'"}')
        sent = HEAD + msg * 100  # about 22 KiB: more than the kernel's buffer takes
        t0 = time.monotonic()
        engine.sendall(sent)
        took = engine_end_after(engine, t0)
        assert SLOW_S <= took < SLOW_S + MARGIN_S, took
        assert pump.slow_drops == 1
        got = recv_to_end(client)
        assert got.startswith(sent)
        assert close_of(got[len(sent):])[0] == 1008


def test_a_client_that_reads_its_messages_is_not_dropped() -> None:
    """A websocket client that keeps reading, and an HTTP client that stops (a download:
    the engine's own download_stall_s is its limit), stay connected past slow_drop_s."""
    with relayed(_native.Pump(slow_drop_s=SLOW_S)) as (pump, _, client, engine):
        msg = text(b'{"type":"event","pad":"' + b"x" * 1000 + b'"}')
        engine.sendall(HEAD)
        assert recv_exactly(client, len(HEAD)) == HEAD
        end = time.monotonic() + 3 * SLOW_S
        while time.monotonic() < end:
            engine.sendall(msg * 20)
            assert recv_exactly(client, 20 * len(msg)) == msg * 20
        assert pump.slow_drops == 0 and pump.connections == 1
    with relayed(_native.Pump(slow_drop_s=SLOW_S), sndbuf=4096) as (pump, _, client, engine):
        body = bytes(200 * 1024)
        head = f"HTTP/1.1 200 OK\r\nContent-Length: {len(body)}\r\n\r\n".encode()
        sent = send_until_held(engine, iter([head, body]), len(head) + len(body))
        assert len(sent) > 128 * 1024
        time.sleep(3 * SLOW_S)
        assert pump.slow_drops == 0 and pump.connections == 1
        assert recv_exactly(client, len(sent)) == sent


def test_a_gateways_defaults_are_the_limits_defaults() -> None:
    """A gateway started without the host's values (``--slow-drop-s``, ``--send-buffer``)
    drops and buffers as the default limits say (it imports nothing of them)."""
    pump = _native.Pump()
    try:
        assert pump.slow_drop_s == Limits().slow_drop_s
    finally:
        pump.stop()
    assert SEND_BUFFER == Limits().socket_send_buffer
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="slow_drop_s"):
            _native.Pump(slow_drop_s=bad)
