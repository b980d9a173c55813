"""Limits and access: each limit answered with a clear error or close reason, roles kept
apart, private rooms (and their replays) closed to anyone without the code, no path out of
the static files or the replays, the websocket origin allow-list. Real server, real
clients, loopback."""

from __future__ import annotations

import asyncio
import json
from typing import Any

import numpy as np
import pytest
from clothball.game.net.client import NetClient, ServerError
from clothball.game.wire import protocol as P
from clothball.game.wire.replay import read_replay
from clothball.server.limits import Limits, parse_origins
from clothball.server.room import RoomSettings
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from tests.server.conftest import FAST, hand_of, http_get, http_json, run, server, until
from tests.server.workers import public_port

HELLO = {"type": "hello", "version": P.PROTOCOL_VERSION}


async def close_of(ws: Any, timeout: float = 10.0) -> tuple[int | None, str]:
    """Read until the server closes; its close code and reason."""
    try:
        while True:
            await asyncio.wait_for(ws.recv(), timeout)
    except ConnectionClosed as e:
        return (e.rcvd.code, e.rcvd.reason) if e.rcvd else (None, "")


async def raw_get(port: int, target: bytes) -> tuple[int, bytes]:
    """A GET with the target exactly as given (no client-side normalisation of '..')."""
    r, w = await asyncio.open_connection("127.0.0.1", port)
    w.write(b"GET " + target + b" HTTP/1.1\r\nHost: localhost\r\n\r\n")
    await w.drain()
    data = await asyncio.wait_for(r.read(), 10)
    w.close()
    if not data:
        return 0, b""  # the HTTP parser refused the request line: closed, nothing served
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split(b" ", 2)[1]), body


# --- limits ------------------------------------------------------------------------------------


def test_connections_per_address_are_limited_with_a_clear_close_reason(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path, limits=Limits(conns_per_address=3)) as srv:
            clients = [await NetClient.connect(srv.ws_url) for _ in range(3)]
            async with connect(srv.ws_url) as ws:  # closed before it can say hello
                code, reason = await close_of(ws)
            assert code == 1008 and "too many connections" in reason and "limit 3" in reason
            await clients.pop().close()
            await until(lambda: len(srv.clients) == 2, 5)
            clients.append(await NetClient.connect(srv.ws_url))  # room again
            assert srv.stats["refused_connections"] == 1
            for c in clients:
                await c.close()

    run(main())


def test_rooms_per_address_and_rooms_in_all_are_limited(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path, limits=Limits(rooms_per_address=2, max_rooms=4)) as srv:
            c = await NetClient.connect(srv.ws_url)
            for _ in range(2):
                assert (await c.request("create_room"))["type"] == "room_created"
            with pytest.raises(ServerError) as e:
                await c.request("create_room")
            assert e.value.code == "too_many_rooms" and "limit 2" in str(e.value)
            # main + 2 = 3 rooms; the fourth comes from "another address" (the limit per
            # address raised), the fifth is one too many for the server
            srv.limits = srv.limits.replace(rooms_per_address=10)
            assert (await c.request("create_room"))["type"] == "room_created"
            with pytest.raises(ServerError) as e:
                await c.request("create_room")
            assert e.value.code == "server_busy" and "4 rooms" in str(e.value)
            await c.close()

    run(main())


def test_spectators_per_room_are_limited(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path, limits=Limits(spectators_per_room=2)) as srv:
            room = srv.main_room
            assert room is not None
            specs = [await NetClient.connect(srv.ws_url, role="spectator", room=room.id)
                     for _ in range(2)]
            with pytest.raises(ServerError) as e:
                await NetClient.connect(srv.ws_url, role="spectator", room=room.id)
            assert e.value.code == "room_full" and "2 spectators" in str(e.value)
            # players are not spectators: a seat is still free
            p = await NetClient.connect(srv.ws_url, role="player", room=room.id)
            for c in [*specs, p]:
                await c.close()

    run(main())


def test_message_size_and_rate_limits_are_configurable_and_say_so(tmp_path) -> None:
    limits = Limits(max_control_bytes=300, max_message_bytes=1000, control_rate=2.0,
                    control_burst=2.0, abuse_drops=20, abuse_window=5.0)
    async def main() -> None:
        async with server(tmp_path, limits=limits) as srv:
            async with connect(srv.ws_url) as ws:
                await ws.send(json.dumps(HELLO))
                await ws.recv()  # welcome (uses no token: the hello is not rate limited)
                await ws.send(json.dumps({"type": "ping", "pad": "x" * 400}))
                err = json.loads(await ws.recv())
                assert err["code"] == "too_big" and "limit 300" in err["message"]
                await ws.send(json.dumps({"type": "ping"}))  # the burst's last token
                assert json.loads(await ws.recv())["type"] == "pong"
                await ws.send(json.dumps({"type": "ping"}))
                err = json.loads(await ws.recv())
                assert err["code"] == "rate_limited" and "at most 2 control" in err["message"]
                for _ in range(30):  # well past abuse_drops within the window: closed
                    await ws.send(json.dumps({"type": "ping"}))
                code, reason = await close_of(ws)
                assert code == 1008 and reason == "too many messages"
            async with connect(srv.ws_url) as ws:
                await ws.send(json.dumps(HELLO))
                await ws.recv()
                await ws.send(b"\0" * 1001)  # over max_message_bytes: closed 1009
                code, _ = await close_of(ws)
                assert code == 1009

    run(main())


def test_limits_from_the_command_line_are_checked() -> None:
    assert Limits().with_setting("conns-per-address=8").conns_per_address == 8
    assert Limits().with_setting("slow_drop_s=0.5").slow_drop_s == 0.5
    for bad, what in [("nope=1", "NAME=VALUE"), ("conns_per_address", "NAME=VALUE"),
                      ("conns_per_address=x", "not a number"), ("slow_drop_s=nan", "finite"),
                      ("max_rooms=0", "> 0"), ("control_rate=-1", "> 0")]:
        with pytest.raises(ValueError, match=what):
            Limits().with_setting(bad)
    # One rule, as docs/security.md states it: a finite number > 0, or 0 for exactly the
    # limits it names (each row then says what 0 means).
    from dataclasses import fields
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[2] / "docs" / "security.md").read_text()
    rule = doc[doc.index("--limit NAME=VALUE"):doc.index("refuses to start")]
    zero_ok = {f.name for f in fields(Limits) if f"`{f.name}`" in rule}
    assert zero_ok == {"admit_load", "admit_lateness_ms", "admit_cores"}
    for f in fields(Limits):
        if f.type not in (int, "int", float, "float"):
            continue
        if f.name in zero_ok:
            assert getattr(Limits().with_setting(f"{f.name}=0"), f.name) == 0
        else:
            with pytest.raises(ValueError, match="> 0"):
                Limits().with_setting(f"{f.name}=0")
    assert parse_origins(None) is None
    assert parse_origins(["https://a.example/"]) == ("https://a.example",)
    with pytest.raises(ValueError, match="origin"):
        parse_origins(["a.example"])


# --- access ------------------------------------------------------------------------------------


def test_a_spectator_cannot_act_as_a_player(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path) as srv:
            room = srv.main_room
            assert room is not None
            spec = await NetClient.connect(srv.ws_url, role="spectator", room=room.id)
            await spec.send_hip(room.anchors[0] + [0.0, 0.05, 0.0])
            assert (await spec.wait_for(lambda m: m["type"] == "error"))["code"] == "not_allowed"
            for t, fields in [("ready", {}), ("start", {}), ("add_bot", {}),
                              ("remove_bot", {"seat": 0})]:
                with pytest.raises(ServerError) as e:
                    await spec.request(t, **fields)
                assert e.value.code == "not_allowed", t
            await asyncio.sleep(0.2)  # (a fixed wait on purpose: nothing happens in it)
            assert all(hand_of(room, k) == (0, None) for k in range(4))  # none moved
            assert all(s.kind == "empty" for s in room.seats)
            await spec.close()

    run(main())


def test_a_player_moves_only_its_own_corner(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path,
                          settings=RoomSettings(bots_allowed=False, unguarded=True)) as srv:
            room = srv.main_room
            assert room is not None
            a = await NetClient.connect(srv.ws_url, role="player", room=room.id, seat=0)
            b = await NetClient.connect(srv.ws_url, role="player", room=room.id, seat=1)
            lifted = room.anchors[0] + [0.0, 0.1, 0.0]
            for _ in range(50):
                await a.send_hip(lifted)
                await asyncio.sleep(0.002)
            await until(lambda: hand_of(room, 0)[0] > 0, 5)
            assert np.allclose(hand_of(room, 0)[1], lifted, atol=1e-6)
            assert hand_of(room, 1) == (0, None)  # b's corner rests at its anchor
            # a HIP aimed at b's corner is outside a's reach box: refused
            await a.send_hip(room.anchors[1])
            err = await a.wait_for(lambda m: m["type"] == "error")
            assert err["code"] == "out_of_range" and "seat 0" in err["message"]
            await asyncio.sleep(0.05)
            assert hand_of(room, 1) == (0, None)
            # no second seat, no taking b's seat away, no removing a human as a bot
            with pytest.raises(ServerError) as e:
                await a.join(room.id, seat=1)
            assert e.value.code == "not_allowed"
            with pytest.raises(ServerError) as e:
                await a.request("remove_bot", seat=1)
            assert e.value.code == "bad_seat"
            assert room.seats[1].conn is not None and room.seats[1].kind == "human"
            await a.close()
            await b.close()

    run(main())


def test_a_private_room_needs_its_code_to_join_watch_or_replay(tmp_path) -> None:
    async def main() -> None:
        settings = RoomSettings(**{**FAST, "first_to": 1}, autoplay=True)
        async with server(tmp_path, bots=4, settings=settings) as srv:
            owner = await NetClient.connect(srv.ws_url, name="owner")
            made = await owner.request("create_room", public=False, first_to=1, countdown=0.2,
                                       reset_speed=3.0, autoplay=True, restart_delay=30)
            rid, code = made["room"], made["code"]
            assert isinstance(code, str) and len(code) >= 8
            listed = (await owner.request("list_rooms"))["rooms"]
            assert rid not in [r["id"] for r in listed]
            assert rid not in [r["id"] for r in (await http_json(srv, "/api/rooms"))["rooms"]]
            for role in ("player", "spectator"):
                for bad in (None, "wrong-code", code[:-1]):
                    with pytest.raises(ServerError) as e:
                        await NetClient.connect(srv.ws_url, role=role, room=rid, code=bad)
                    assert e.value.code == "bad_code", (role, bad)
            spec = await NetClient.connect(srv.ws_url, role="spectator", room=rid, code=code)
            # the owner fills the private room with bots; both rooms play a round
            await owner.join(rid, role="spectator", code=code)
            for _ in range(4):
                await owner.request("add_bot")
            saved = await spec.wait_event("replay_saved", timeout=40, since=0)
            await until(lambda: srv.stats["rounds_saved"] >= 2, 40, "a public round saved")
            private_id = saved["id"]
            public = await http_json(srv, "/api/replays")
            assert public["total"] >= 1 and all(r["room_id"] != rid for r in public["replays"])
            assert not any(r["private"] for r in public["replays"])
            for q in (f"?room={rid}", f"?room={rid}&code=wrong"):
                assert (await http_json(srv, "/api/replays" + q))["replays"] == []
            mine = await http_json(srv, f"/api/replays?room={rid}&code={code}")
            assert mine["total"] >= 1 and mine["replays"][0]["private"] is True
            assert private_id in [r["id"] for r in mine["replays"]]
            for q in ("", "?code=wrong"):
                status, _, _ = await http_get(srv, f"/api/replays/{private_id}{q}")
                assert status == 404
            status, body, _ = await http_get(srv, f"/api/replays/{private_id}?code={code}")
            assert status == 200 and read_replay(body)[0]["id"] == private_id
            assert "code" not in read_replay(body)[0]  # only a hash of it is kept
            # the ?player= filter (issue 6): rounds where a seat had that name
            bot0 = await http_json(srv, "/api/replays?player=bot-0")
            assert bot0["total"] == public["total"]
            none = await http_json(srv, "/api/replays?player=nobody")
            assert none == {"replays": [], "total": 0}
            status, body, _ = await http_get(srv, "/api/replays?player=" + "x" * 40)
            assert status == 400 and b"player" in body
            await spec.close()
            await owner.close()

    run(main())


TRAVERSALS = [
    b"/static/../../server/app.py", b"/static/%2e%2e/%2e%2e/server/app.py",
    b"/static/..%2f..%2fserver%2fapp.py", b"/static/%2e%2e%2f%2e%2e%2fpyproject.toml",
    b"/static//etc/passwd", b"/static/%2fetc%2fpasswd", b"/static/..\\..\\server\\app.py",
    b"/static/index.html%00.png", b"/static/....//....//etc/passwd",
    b"/static/web/../../../../etc/passwd", b"/api/replays/../index.sqlite",
    b"/api/replays/..%2findex.sqlite", b"/api/replays/%2e%2e%2findex.sqlite",
    b"/api/replays/../../etc/passwd", b"/api/replays/index.sqlite", b"/api/replays/.cbr",
    b"/api/replays/%00", b"/../../etc/passwd", b"/%2e%2e/%2e%2e/etc/passwd",
]


def test_no_path_traversal_through_static_files_or_replays(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path) as srv:
            (tmp_path / "replays" / "secret.cbr").write_bytes(b"not for you")
            for target in TRAVERSALS:
                status, body = await raw_get(srv.port, target)
                assert status in (0, 400, 404), (target, status, body[:200])
                assert b"import" not in body and b"root:" not in body and b"SQLite" not in body
            status, body = await raw_get(srv.port, b"/static/index.html")
            assert status == 200 and b"<html" in body.lower()

    run(main())


def test_the_websocket_origin_allow_list(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path, origins=("https://good.example",)) as srv:
            with pytest.raises(InvalidStatus) as e:
                async with connect(srv.ws_url, origin="https://evil.example"):
                    pass
            assert e.value.response.status_code == 403
            assert b"https://evil.example" in e.value.response.body
            for origin in ("https://good.example", None):  # None: not a browser
                async with connect(srv.ws_url, origin=origin) as ws:
                    await ws.send(json.dumps(HELLO))
                    assert json.loads(await ws.recv())["type"] == "welcome"
            # the server's own pages (served from the port clients are given) stay allowed
            own = f"http://127.0.0.1:{public_port(srv)}"
            async with connect(srv.ws_url, origin=own) as ws:
                await ws.send(json.dumps(HELLO))
                assert json.loads(await ws.recv())["type"] == "welcome"
        async with server(tmp_path) as srv:  # the default: only its own pages (issue 22)
            with pytest.raises(InvalidStatus) as e:
                async with connect(srv.ws_url, origin="https://elsewhere.example"):
                    pass
            assert e.value.response.status_code == 403

    run(main())


def test_lobby_clients_get_the_room_list_pushed_when_it_changes(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path) as srv:
            watcher = await NetClient.connect(srv.ws_url)
            maker = await NetClient.connect(srv.ws_url)
            start = watcher.received_total
            made = await maker.request("create_room", name="pushed")
            pushed = await watcher.wait_for(
                lambda m: m["type"] == "rooms" and made["room"] in [r["id"] for r in m["rooms"]],
                5, since=start)
            assert [r["name"] for r in pushed["rooms"] if r["id"] == made["room"]] == ["pushed"]
            # a seat taken is a change too
            start = watcher.received_total
            p = await NetClient.connect(srv.ws_url, role="player", room=made["room"])
            pushed = await watcher.wait_for(lambda m: m["type"] == "rooms", 5, since=start)
            room = [r for r in pushed["rooms"] if r["id"] == made["room"]][0]
            assert room["seats"][0]["kind"] == "human"
            await p.close()
            await maker.close()
            await watcher.close()

    run(main())
