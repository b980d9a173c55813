"""The server's hot paths give exactly what the plain code gives: CORNER messages packed four
at a time, HIPs decoded in one unpack, binary messages handled as they arrive (in order
with the text messages around them), CORNER and MESH written without waking the sender;
and ``clothball bench --server --json FILE`` writes FILE."""

from __future__ import annotations

import asyncio
import json
import math
import struct
import subprocess
import sys

import numpy as np
import pytest
from clothball.game.wire import protocol as P
from clothball.server.bench import loadbench
from clothball.server.room import RoomSettings
from hypothesis import given, settings
from hypothesis import strategies as st
from websockets.asyncio.client import connect

from tests.conftest import examples
from tests.server.conftest import hand_of, run, server, until

_f64 = st.floats(allow_nan=True, allow_infinity=True, width=64)
_vec = st.tuples(_f64, _f64, _f64)


@given(frame=st.integers(0, 2**62), server_time=_f64,
       rows=st.lists(st.tuples(_vec, _vec, _vec, st.integers(0, 2**40), _f64),
                     min_size=4, max_size=4),
       stiffness=_f64, bp=_vec, bv=_vec)
@settings(max_examples=examples(300), deadline=None)
def test_encode_corners_is_encode_corner_four_times(frame, server_time, rows, stiffness, bp,
                                                   bv) -> None:
    pos = [r[0] for r in rows]
    vel = [r[1] for r in rows]
    force = [r[2] for r in rows]
    applied = [(r[3], r[4]) for r in rows]
    def outcome(fn):
        try:
            return fn()
        except (struct.error, OverflowError) as e:  # beyond float32: both refuse alike
            return type(e)

    want = outcome(lambda: [
        P.encode_corner(frame, s, pos[s], vel[s], force[s], stiffness, bp, bv, applied[s][0],
                        applied[s][1], server_time) for s in range(4)])
    got = outcome(lambda: P.encode_corners(frame, server_time, pos, vel, force, stiffness, bp,
                                           bv, applied))
    assert got == want


def _outcome(fn, data):
    try:
        h = fn(data)
    except P.ProtocolError as e:
        return ("error", e.code, e.message)
    return ("ok", h.position, h.seq, h.time)


@given(st.one_of(
    st.binary(min_size=0, max_size=40),
    st.binary(min_size=P.HIP_SIZE, max_size=P.HIP_SIZE),
    st.tuples(st.integers(0, 255), st.integers(0, 255), st.integers(0, 2**16 - 1),
              st.integers(0, 2**32 - 1), _f64, st.floats(width=32), st.floats(width=32),
              st.floats(width=32)).map(lambda v: P.HIP_MSG.pack(*v)),
    st.tuples(st.floats(width=32), st.floats(width=32), st.floats(width=32),
              st.integers(0, 2**32 - 1), _f64).map(
        lambda v: P.encode_hip(v[:3], v[3], v[4]) if math.isfinite(v[4])
        else P.encode_hip((0.0, 0.0, 0.0), v[3], 0.0)),
))
@settings(max_examples=examples(2000), deadline=None)
def test_decode_hip_fast_path_is_the_checked_decoder(data) -> None:
    # NaN never reaches an "ok" outcome, so plain equality is right
    assert _outcome(P.decode_hip, data) == _outcome(P._decode_hip_checked, data)


def test_binary_messages_keep_their_order_with_text_ones(tmp_path) -> None:
    """A HIP written in the same packet as the hello that seats the player is handled after
    the hello; an erroneous HIP written right behind a ping is answered after the pong."""

    async def main() -> None:
        async with server(tmp_path,
                          settings=RoomSettings(bots_allowed=False, unguarded=True)) as srv:
            room = srv.main_room
            assert room is not None
            inside = room.anchors[0] + [0.0, 0.05, 0.0]
            outside = room.anchors[0] + [0.0, 50.0, 0.0]
            hello = {"type": "hello", "version": P.PROTOCOL_VERSION, "role": "player",
                     "room": room.id, "seat": 0, "id": 0}
            url = srv.ws_url
            for _ in range(2):  # a redirect (two processes): the same, where the room lives
                ws = await connect(url, compression=None)
                # both frames in one write: the server reads them in one go
                ws.protocol.send_text(P.encode_json(hello).encode())
                ws.protocol.send_binary(P.encode_hip(inside, 1, 0.5))
                ws.send_data()
                while (first := json.loads(await asyncio.wait_for(ws.recv(), 10)))["type"] \
                        not in ("joined", "redirect", "error"):
                    pass
                if first["type"] != "redirect":
                    break
                await ws.close()
                url = first["url"]
            got: list[dict] = [first]

            async def until_type(t: str) -> dict:
                while True:
                    m = await asyncio.wait_for(ws.recv(), 10)
                    if isinstance(m, str):
                        got.append(json.loads(m))
                        if got[-1]["type"] == t:
                            return got[-1]

            assert first["type"] == "joined", first
            await until(lambda: hand_of(room, 0)[0] == 1, 5, "the first HIP")
            assert not [m for m in got if m["type"] == "error"]
            for i in range(20):  # the handler is in its read loop now: the fast path
                ws.protocol.send_text(P.encode_json({"type": "ping", "id": 100 + i}).encode())
                ws.protocol.send_binary(P.encode_hip(outside, 2 + i, 0.5))
                ws.send_data()
                pong = await until_type("pong")
                assert pong["re"] == 100 + i
                err = await until_type("error")
                assert err["code"] == "out_of_range"
                ws.protocol.send_binary(P.encode_hip(inside, 1000 + i, 0.5))
                ws.send_data()
            await until(lambda: hand_of(room, 0)[0] == 1019, 5, "the last HIP")
            seen = [m["type"] for m in got if m["type"] in ("pong", "error")]
            assert seen == ["pong", "error"] * 20
            # (HIPs a gateway took are counted when it reports, once a second)
            await until(lambda: srv.stats["messages_in"] >= 1 + 60, 5, "the messages counted")
            await ws.close()

    run(main())


def test_corners_reach_the_player_in_frame_order(tmp_path) -> None:
    """CORNER messages written straight from the frame hand-over arrive whole, newest
    last (how many a second is the server bench's to measure, not this test's)."""

    async def main() -> None:
        from clothball.game.net.client import NetClient

        async with server(tmp_path,
                          settings=RoomSettings(bots_allowed=False, unguarded=True)) as srv:
            room = srv.main_room
            assert room is not None
            p = await NetClient.connect(srv.ws_url, role="player", room=room.id, seat=1)
            frames: list[int] = []
            p.on_corner = lambda c: frames.append(c.frame)
            await until(lambda: len(frames) > 150, 30, "150 corners")
            assert p.counts["bad"] == 0
            assert all(b > a for a, b in zip(frames, frames[1:], strict=False))
            conn = next(c for c in srv.clients if c.seat == 1)
            # from the engine's lane; or, where the player came through a gateway that serves
            # its lane, from the gateway: the engine sent only its few replies
            assert conn.sent >= len(frames) if not conn.relayed_lane else conn.sent < 20, \
                conn.sent
            await p.close()

    run(main())


def test_write_json_writes_the_file_or_says_to_print(tmp_path, capsys) -> None:
    dest = tmp_path / "out.json"
    assert loadbench._write_json({"a": 1}, str(dest)) is False
    assert json.loads(dest.read_text()) == {"a": 1}
    assert f"wrote {dest}" in capsys.readouterr().out
    assert loadbench._write_json({"a": 1}, True) is True
    assert loadbench._write_json({"a": 1}, False) is False
    assert loadbench._write_json({"a": 1}, None) is False


@pytest.mark.slow
def test_bench_server_json_file_is_written(tmp_path) -> None:
    dest = tmp_path / "server.json"
    out = subprocess.run(
        [sys.executable, "-m", "clothball.game.cli", "bench", "--server", "--seconds", "1",
         "--players", "1", "--spectators", "2", "--hip-rate", "100", "--server-n", "12",
         "--json", str(dest)],
        capture_output=True, text=True, timeout=180, check=True,
    )
    r = json.loads(dest.read_text())
    assert r["players"] == 1 and r["spectators"] == 2 and r["n"] == 12
    assert r["hip_to_corner_ms"]["count"] > 0
    assert set(r["targets"]) == {"hip_to_corner_p99_le_5ms", "frame_lateness_p99_le_5ms",
                                 "all_spectators_30hz"}
    assert f"wrote {dest}" in out.stdout
    assert "HIP -> corner state" in out.stdout  # the summary is still printed
    assert not out.stdout.lstrip().startswith("{")  # not the JSON
    assert np.isfinite(r["frame_lateness_ms"]["p99"])
