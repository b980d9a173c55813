"""The gateway's pump (``_native.Pump``, native/net/pump.hpp) on socket pairs, each side
played by the test: the bytes both ways as they were sent (the PROXY line first), the
engine's lane messages taken out of its stream and told, half-closes passed on, the
engine's end told with where the stream stood, the gateway's tail written before the end,
and backpressure: a client that stops reading stops the engine's side being read, and an
engine that hangs up meanwhile is read to its end once the client reads again. The lanes'
HIPs and CORNERs through a real host are ``test_workers.py``'s."""

from __future__ import annotations

import json
import socket
import time

import pytest
from clothball import _native
from clothball.game.wire import protocol as P
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


@pytest.fixture
def relay():
    """A pump relaying one connection: (pump, conn, the client's end, the engine's end)."""
    pump = _native.Pump()
    client, c_pump = socket.socketpair()
    engine, e_pump = socket.socketpair()
    c_pump.setblocking(False)
    e_pump.setblocking(False)
    conn = pump.add(c_pump.detach(), e_pump.detach(), b"PROXY TCP4 1.2.3.4 5.6.7.8 1 2\r\n",
                    False)
    yield pump, conn, client, engine
    pump.stop()
    client.close()
    engine.close()


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
