"""Every bad input gets a clear error; the message or connection is refused; the room runs
on and nothing stored is lost."""

from __future__ import annotations

import asyncio
import json
import math
import struct
from typing import Any

import pytest
from clothball.game.net.client import NetClient, ServerError
from clothball.game.wire import protocol as P
from clothball.server.limits import Limits
from clothball.server.room import RoomSettings
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from tests.server.conftest import http_json, run, server, until
from tests.server.workers import service_stats

HELLO = {"type": "hello", "version": P.PROTOCOL_VERSION}


async def recv_json(ws: ClientConnection, timeout: float = 5.0) -> dict[str, Any]:
    """The next JSON message within ``timeout`` s, skipping binary streams."""

    async def first() -> dict[str, Any]:
        while True:
            m = await ws.recv()
            if isinstance(m, str):
                return json.loads(m)

    return await asyncio.wait_for(first(), timeout)


async def next_error(ws: ClientConnection, timeout: float = 5.0) -> dict[str, Any]:
    while True:
        m = await recv_json(ws, timeout)
        if m["type"] == "error":
            return m


async def error_for(ws: ClientConnection, msg: str | bytes) -> dict[str, Any]:
    """Send ``msg``; the error it gets. A ``redirect`` (the room lives on another process,
    ``CLOTHBALL_TEST_WORKERS=2``) is followed as the bundled clients follow one: the same
    request, with the redirect's ``with`` fields, from a new connection there."""
    await ws.send(msg)
    while True:
        m = await recv_json(ws)
        if m["type"] == "error":
            return m
        if m["type"] == "redirect":
            assert isinstance(msg, str), m
            async with connect(m["url"]) as there:
                await there.send(json.dumps(HELLO))
                await there.send(json.dumps({**json.loads(msg), **m.get("with", {})}))
                return await next_error(there)


async def open_seated(url: str, hello: dict[str, Any]) -> tuple[ClientConnection,
                                                                 dict[str, Any]]:
    """A connection whose hello seats it (following a redirect, as ``error_for``); it and
    its ``joined``."""
    for _ in range(3):
        ws = await connect(url)
        await ws.send(json.dumps(hello))
        while (m := await recv_json(ws))["type"] not in ("joined", "redirect"):
            pass
        if m["type"] == "joined":
            return ws, m
        await ws.close()
        url = m["url"]
    raise AssertionError(f"redirected too often (last to {url})")


async def closed_with(ws: ClientConnection) -> int | None:
    try:
        while True:
            await asyncio.wait_for(ws.recv(), 5.0)
    except ConnectionClosed as e:
        return e.rcvd.code if e.rcvd else None


@pytest.mark.parametrize(
    ("first", "code"),
    [
        (b"\x01\x01binary first", "bad_message"),
        ('{"type": "join"}', "bad_message"),
        ("not json", "bad_json"),
        ('{"type": "hello", "version": 99}', "bad_version"),
        ('{"type": "hello"}', "bad_message"),  # a missing field, as in any message
        # the integer 1 only: JSON tells 1.0 and true from 1 (Python's == does not)
        ('{"type": "hello", "version": 1.0}', "bad_version"),
        ('{"type": "hello", "version": true}', "bad_version"),
        ('{"type": "hello", "version": "1"}', "bad_version"),
        ('{"type": "hello", "version": 1, "name": 5}', "bad_message"),
        # a hello that cannot be welcomed as asked: no such role, a join without a room
        ('{"type": "hello", "version": 1, "role": "king"}', "bad_message"),
        ('{"type": "hello", "version": 1, "role": "player"}', "bad_message"),
        ('{"type": "hello", "version": 1, "role": "spectator", "seat": 0}', "bad_message"),
        # a request id that is neither a short string nor a whole number
        ('{"type": "hello", "version": 1, "id": 1.5}', "bad_message"),
        ('{"type": "hello", "version": 1, "id": null}', "bad_message"),
    ],
)
def test_a_bad_first_message_is_refused_and_closes(tmp_path, first, code) -> None:
    async def main() -> None:
        async with server(tmp_path) as srv:
            async with connect(srv.ws_url) as ws:
                await ws.send(first)
                err = await next_error(ws)
                assert err["code"] == code and err["message"]
                assert await closed_with(ws) == 1008
            assert srv.main_room is not None and srv.main_room.sim.alive

    run(main())


def test_no_hello_in_time_closes(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path, hello_timeout=0.3) as srv:
            async with connect(srv.ws_url) as ws:
                err = await next_error(ws)
                assert err["code"] == "bad_message" and "hello" in err["message"]
                assert await closed_with(ws) == 1008

    run(main())


def test_bad_messages_after_hello_get_errors_and_the_room_runs_on(tmp_path) -> None:
    async def main() -> None:
        settings = RoomSettings(bots_allowed=False, unguarded=True)
        # A HIP rate far below what any machine reads, so that the flood below is over it
        # however slowly a loaded machine reads it (at the default 1200/s, a server taking
        # over ~2.2 s for the 3000 HIPs would refuse none; here it takes ~0.1 s).
        limits = Limits(binary_rate=100.0, binary_burst=50.0)
        async with server(tmp_path, settings=settings, limits=limits) as srv:
            room = srv.main_room
            assert room is not None
            rid = room.id
            player = await NetClient.connect(srv.ws_url, role="player", room=rid, seat=0)
            reach = player.reach
            assert reach is not None
            async with connect(srv.ws_url) as ws:
                await ws.send(json.dumps(HELLO))
                assert (await recv_json(ws))["type"] == "welcome"
                cases: list[tuple[str | bytes, str]] = [
                    ("{oops", "bad_json"),
                    ("[1, 2, 3]", "bad_json"),
                    ('{"kind": "ping"}', "bad_message"),
                    ('{"type": "fly"}', "unknown_type"),
                    ('{"type": "__init__"}', "unknown_type"),
                    ('{"type": "hello", "version": 1}', "not_allowed"),
                    ('{"type": "x", "v": NaN}', "bad_json"),
                    ('{"type": "ping", "t": 1e400}', "bad_message"),  # parses as inf
                    ('{"type": "ready"}', "not_allowed"),
                    ('{"type": "start"}', "not_allowed"),
                    (P.encode_hip((0, 0, 0), 1, 0.0), "not_allowed"),  # not a player
                    ('{"type": "join", "room": "nope", "role": "player"}', "unknown_room"),
                    ('{"type": "join", "room": 5}', "unknown_room"),
                    (json.dumps({"type": "join", "room": rid, "role": "player", "seat": 7}),
                     "bad_seat"),
                    (json.dumps({"type": "join", "room": rid, "role": "player", "seat": 0}),
                     "bad_seat"),  # taken
                    (json.dumps({"type": "join", "room": rid, "role": "king"}), "bad_message"),
                    (json.dumps({"type": "join", "token": "x" * 30}), "bad_token"),
                    (json.dumps({"type": "create_room", "first_to": 0}), "bad_message"),
                    (json.dumps({"type": "create_room", "countdown": 1e9}), "bad_message"),
                    (json.dumps({"type": "create_room", "scene": "../../etc"}), "bad_message"),
                    (json.dumps({"type": "create_room", "name": "a\u0000b"}), "bad_message"),
                    (json.dumps({"type": "create_room", "public": "yes"}), "bad_message"),
                    (json.dumps({"type": "ping", "t": "now"}), "bad_message"),
                    ('{"type": "ping", "pad": "' + "x" * 5000 + '"}', "too_big"),
                ]
                for msg, code in cases:
                    err = await error_for(ws, msg)
                    assert err["code"] == code, (msg, err)
                    assert isinstance(err["message"], str) and err["message"]
                    await asyncio.sleep(0.06)  # stay under the control-message rate
                # replies echo the request id, errors too
                await ws.send(json.dumps({"type": "fly", "id": "abc"}))
                assert (await next_error(ws))["re"] == "abc"
                # the connection is still good
                await ws.send(json.dumps({"type": "ping", "t": 1.5, "id": 9}))
                pong = await recv_json(ws)
                assert pong["type"] == "pong" and pong["t"] == 1.5 and pong["re"] == 9

            # a seated player's bad HIPs
            ws, joined = await open_seated(srv.ws_url, {**HELLO, "role": "player", "room": rid,
                                                        "seat": 1, "corner_rate": 5,
                                                        "mesh": False})
            async with ws:
                c = joined["reach"]["centre"]
                bad_hips: list[tuple[bytes, str]] = [
                    (P.encode_hip((math.nan, 0, 0), 1, 0.0), "bad_binary"),
                    (P.encode_hip((0, math.inf, 0), 2, 0.0), "bad_binary"),
                    (P.encode_hip((0, 0, 0), 3, math.inf), "bad_binary"),
                    (P.encode_hip((0, 0, 0), 4, 0.0)[:20], "bad_binary"),
                    (P.encode_hip((0, 0, 0), 5, 0.0) + b"\0", "bad_binary"),
                    (b"\x01\x02" + P.encode_hip((0, 0, 0), 6, 0.0)[2:], "bad_version"),
                    (b"\x03" + P.encode_hip((0, 0, 0), 6, 0.0)[1:], "bad_binary"),
                    (b"", "bad_binary"),
                    (P.encode_hip((c[0] + 5.0, c[1], c[2]), 7, 0.0), "out_of_range"),
                    (P.encode_hip((1e30, 0, 0), 8, 0.0), "out_of_range"),
                ]
                for data, code in bad_hips:
                    await ws.send(data)
                    err = await next_error(ws)
                    assert err["code"] == code, (data, err)
                    await asyncio.sleep(0.25)  # stay under the error-reply rate
                # a flood of control messages: the extra ones are refused, the link stays
                for i in range(120):
                    await ws.send(json.dumps({"type": "ping", "id": i}))
                got: list[dict[str, Any]] = []

                def seen() -> bool:
                    kinds = [m.get("code", m["type"]) for m in got]
                    return "pong" in kinds and "rate_limited" in kinds

                # The replies until a second passes without one, and at least until a pong
                # and a refusal came (however long a loaded machine takes to send them).
                while True:
                    try:
                        got.append(await recv_json(ws, 1.0 if seen() else 30.0))
                    except TimeoutError:
                        break
                kinds = [m.get("code", m["type"]) for m in got]
                assert "pong" in kinds and "rate_limited" in kinds
                assert kinds.count("pong") < 120
                # a flood of HIPs past the rate: refused, the link stays
                hip = P.encode_hip(c, 1, 0.0)
                for _ in range(3000):
                    await ws.send(hip)
                errs = []
                while True:  # (as above: at least until a refusal came)
                    limited = any(e["code"] == "rate_limited" for e in errs)
                    try:
                        m = await recv_json(ws, 1.0 if limited else 30.0)
                    except TimeoutError:
                        break
                    if m["type"] == "error":
                        errs.append(m)
                assert any(e["code"] == "rate_limited" for e in errs), (errs, srv.stats)
                assert len(errs) < 100  # error replies are rate limited too
                await asyncio.sleep(1.0)  # (a fixed wait: the rate limit's bucket refills)
                await ws.send(json.dumps({"type": "ping", "id": "alive"}))
                while (m := await recv_json(ws))["type"] != "pong":
                    pass
                # larger than any message may be: the connection is closed (1009)
                await ws.send(b"\0" * (P.MAX_MESSAGE_BYTES + 1))
                assert await closed_with(ws) == 1009

            # the room ran on through all of it, and the good player still gets its corners
            # (whether it kept its 1 kHz pace is measured by the load bench, not asserted
            # here: on a shared 2-core machine a stall of 50 ms skips frames by design)
            # (counted from the room's frame now: the player's newest CORNER may be a few
            # frames behind it, so counting from that one raced the room's own count)
            sim0 = room.sim.stats.frames
            await until(lambda: player.corner.frame > sim0 + 100, 10, "corners after the abuse")
            assert room.sim.alive and room.sim.stats.frames > sim0 + 100
            rooms = await http_json(srv, "/api/rooms")
            assert rooms["rooms"][0]["id"] == rid
            stats = await service_stats(srv)
            assert stats["bad_messages"] >= 30
            await player.close()

    run(main())


def test_a_bad_request_id_is_refused_without_re_and_the_request_is_not_done(tmp_path
                                                                             ) -> None:
    async def main() -> None:
        async with server(tmp_path) as srv:
            async with connect(srv.ws_url) as ws:
                await ws.send(json.dumps(HELLO))
                assert (await recv_json(ws))["type"] == "welcome"
                for bad in ["x" * 65, 1.5, None, [1], {"a": 1}, True, 2**53 + 1, "a\u202eb"]:
                    await ws.send(json.dumps({"type": "ping", "t": 1.0, "id": bad}))
                    # not a pong: the ping was not answered (the pushed room list skipped)
                    while (err := await recv_json(ws))["type"] == "rooms":
                        pass
                    assert err["type"] == "error" and err["code"] == "bad_message", (bad, err)
                    assert "re" not in err and "'id'" in err["message"], (bad, err)
                    await asyncio.sleep(0.25)  # stay under the error-reply rate
                # the edges of what is allowed, echoed exactly
                for good in ["x" * 64, 2**53, -(2**53), 0, ""]:
                    await ws.send(json.dumps({"type": "ping", "id": good}))
                    while (pong := await recv_json(ws))["type"] == "rooms":
                        pass
                    assert pong["type"] == "pong" and pong["re"] == good, (good, pong)

    run(main())


def test_bot_seats_out_of_range_are_bad_seat_and_hip_flags_are_refused(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path) as srv:
            assert srv.main_room is not None  # no host: any seated player controls it
            # seat 9 names no seat, as join says
            ws, joined = await open_seated(srv.ws_url, {**HELLO, "role": "player",
                                                        "room": srv.main_room.id,
                                                        "seat": 2, "mesh": False,
                                                        "corner_rate": 5})
            async with ws:
                for msg in ({"type": "remove_bot", "seat": 9}, {"type": "add_bot", "seat": 9},
                            {"type": "remove_bot", "seat": -1}):
                    err = await error_for(ws, json.dumps(msg))
                    assert err["code"] == "bad_seat" and "0..3" in err["message"], (msg, err)
                    await asyncio.sleep(0.25)  # stay under the error-reply rate
                err = await error_for(ws, json.dumps({"type": "remove_bot", "seat": "9"}))
                assert err["code"] == "bad_message"  # of the wrong type: a bad message
                await asyncio.sleep(0.25)  # stay under the error-reply rate
                # a HIP whose header sets a flag no version defines for it: refused
                c = joined["reach"]["centre"]
                hip = bytearray(P.encode_hip(c, 1, 0.0))
                hip[2:4] = (1).to_bytes(2, "little")
                await ws.send(bytes(hip))
                err = await next_error(ws)
                assert err["code"] == "bad_binary" and "flags" in err["message"], err

    run(main())


def test_lobby_connection_cannot_play_and_a_full_room_says_so(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path) as srv:
            room = srv.main_room
            assert room is not None
            players = [await NetClient.connect(srv.ws_url, role="player", room=room.id)
                       for _ in range(4)]
            assert sorted(p.seat for p in players) == [0, 1, 2, 3]
            with pytest.raises(ServerError) as e:
                await NetClient.connect(srv.ws_url, role="player", room=room.id)
            assert e.value.code == "room_full"
            spec = await NetClient.connect(srv.ws_url, role="spectator", room=room.id)
            await spec.send_hip((0, 1, 0))
            err = await spec.wait_for(lambda m: m["type"] == "error")
            assert err["code"] == "not_allowed"
            with pytest.raises(ServerError) as e:
                await spec.join(room.id)
            assert e.value.code == "not_allowed"  # already in a room
            await until(lambda: all(p.corner is not None for p in players), 5)
            for p in [*players, spec]:
                await p.close()

    run(main())


def test_mesh_header_fields_are_little_endian_and_documented() -> None:
    data = P.encode_hip((1.0, 2.0, 3.0), 7, 0.5)
    assert struct.unpack_from("<BBHId", data) == (P.HIP, 1, 0, 7, 0.5)
