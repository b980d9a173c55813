"""Hostile input that one client could turn against everyone on the host (issue 22):
strings that break encodings downstream, malformed HTTP requests, expensive index queries,
what public endpoints tell of private rooms, and the websocket origin policy. Real server,
real clients, loopback; an independent reference for what is accepted where one is needed."""

from __future__ import annotations

import asyncio
import json
import logging
import random
import sqlite3
import threading
import unicodedata
import urllib.parse
from typing import Any

import pytest
from clothball.game.net.client import NetClient, ServerError
from clothball.game.wire import protocol as P
from clothball.game.wire.replay import read_replay
from clothball.server.limits import Limits, parse_origins
from clothball.server.room import RoomSettings
from clothball.server.storage.index import access_key
from clothball.server.storage.sqlite import SqliteIndex
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from tests.conftest import examples
from tests.server.conftest import (
    FAST,
    ErrorLog,
    LiveServer,
    http_get,
    http_json,
    live_server,
    run,
    server,
    until,
)
from tests.server.workers import processes, public_port, service_stats

HELLO = {"type": "hello", "version": P.PROTOCOL_VERSION}

# --- 1. client strings ---------------------------------------------------------------------


def expected_text(v: str, max_len: int) -> str | None:
    """The reference: what a valid client string becomes, or None if it must be refused.
    Scalar values only (no code point in the surrogate block), NFC, at most ``max_len``
    code points, no C0/DEL/C1 controls, no bidi embedding, override or isolate."""
    if any(0xD800 <= ord(c) <= 0xDFFF for c in v):
        return None
    n = unicodedata.normalize("NFC", v)
    if len(n) > max_len:
        return None
    if any(ord(c) < 0x20 or 0x7F <= ord(c) <= 0x9F or 0x202A <= ord(c) <= 0x202E
           or 0x2066 <= ord(c) <= 0x2069 for c in n):
        return None
    return n


def as_given(v: str, max_len: int, default: str) -> str | None:
    """``expected_text``, where an empty string stands for ``default``."""
    want = expected_text(v, max_len)
    return default if want == "" else want


SPECIAL = ["\ud800x", "x\udfff", "\u200fמשה\u200e", "\u202eevil", "a\x00b", "tab\there",
           "e\u0301" * 32, "😀" * 32, "😀" * 33, "x" * 10_000, "\u0085", "Zoë", "\ufeffbom",
           "\U0010ffff", "", " ", "ﬃ", "Å"]


@pytest.mark.parametrize("v", SPECIAL + ["x" * 32, "x" * 33])
def test_field_str_checks_and_normalises_client_strings(v: str) -> None:
    want = expected_text(v, 32)
    if want is None:
        with pytest.raises(P.ProtocolError) as e:
            P.field_str({"name": v}, "name", max_len=32)
        assert e.value.code == "bad_message" and "'name'" in e.value.message
        json.dumps(e.value.to_message()).encode()  # the error itself is sendable
    else:
        assert P.field_str({"name": v}, "name", max_len=32) == want
        want.encode("utf-8")


def test_a_bad_name_is_refused_at_hello_and_a_good_one_normalised(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path) as srv:
            for bad in ("\ud800x", "a\x00b", "\u202eevil", "😀" * 33):
                with pytest.raises(ServerError) as e:
                    await NetClient.connect(srv.ws_url, name=bad)
                assert e.value.code == "bad_message" and "'name'" in str(e.value)
            c = await NetClient.connect(srv.ws_url, name="Zoe\u0308")
            assert c.welcome["name"] == "Zoë"
            with pytest.raises(ServerError) as e:
                await c.request("create_room", name="room\udc80")
            assert e.value.code == "bad_message" and "'name'" in str(e.value)
            await c.close()

    run(main())


@pytest.fixture(scope="module")
def rounds_server(tmp_path_factory: pytest.TempPathFactory):
    lim = Limits(max_rooms=200, rooms_per_address=200, index_rate=1000, index_burst=1000)
    with live_server(tmp_path_factory.mktemp("names"), limits=lim,
                     room_settings=RoomSettings(bots_allowed=False, unguarded=True)) as live:
        yield live


names = st.one_of(
    st.text(st.characters(exclude_categories=()), max_size=40),  # surrogates included
    st.sampled_from(SPECIAL),
)


@settings(max_examples=examples(6), deadline=None, suppress_health_check=list(HealthCheck))
@given(room_name=names, player_names=st.lists(names, min_size=2, max_size=2))
@example(room_name="\u202eroom", player_names=["\ud800x", "\u200fמשה"])
@example(room_name="😀", player_names=["a\x00b", "e\u0301" * 32])
@example(room_name="x" * 10_000, player_names=["x" * 10_000, "😀" * 32])
def test_any_string_through_a_recorded_round(rounds_server: LiveServer, room_name: str,
                                             player_names: list[str]) -> None:
    """join -> events -> a recorded round -> listed -> downloaded -> decoded: every string
    is either refused at the edge with a clear error or comes out the same everywhere."""
    live = rounds_server
    url = live.srv.ws_url

    async def main() -> None:
        owner = await NetClient.connect(url, name="owner")
        opts = dict(first_to=1, countdown=0.2, reset_speed=3.0, restart_delay=30,
                    bots_allowed=False, unguarded=True)
        want_room = as_given(room_name, 48, "room")
        made = None
        if len(P.encode_json({"type": "create_room", "name": room_name, **opts})) > 4096:
            # too big to read at all, so the error cannot name the request it refuses
            start = owner.received_total
            await owner.send_json({"type": "create_room", "name": room_name, **opts})
            err = await owner.wait_for(lambda m: m["type"] == "error", 10, since=start)
            assert err["code"] == "too_big"
        else:
            try:
                made = await owner.request("create_room", name=room_name, **opts)
                assert want_room is not None and made["state"]["name"] == want_room
            except ServerError as e:
                assert want_room is None and e.code == "bad_message" and "'name'" in str(e)
        if made is None:
            made = await owner.request("create_room", name="fallback", **opts)
            want_room = "fallback"
        rid = made["room"]
        players, seated = [], []
        for name in player_names:
            want = as_given(name, 32, "guest")
            try:
                p = await NetClient.connect(url, name=name, role="player", room=rid)
            except ServerError as e:
                assert want is None, (name, e)
                # too_big: a name of 10 000 characters does not fit a hello at all
                assert e.code == "too_big" or (e.code == "bad_message" and "'name'" in str(e))
                continue
            assert want is not None and p.welcome["name"] == want
            players.append(p)
            seated.append(want)
        if not players:
            players.append(await NetClient.connect(url, name="plain", role="player", room=rid))
            seated.append("plain")
        for p in players:
            await p.request("ready")
        saved = await players[0].wait_event("replay_saved", timeout=60, since=0)
        listed = json.loads(await asyncio.to_thread(
            live_get, live, f"/api/replays?room={urllib.parse.quote(rid)}"))
        row = next(r for r in listed["replays"] if r["id"] == saved["id"])
        assert row["room_name"] == want_room
        assert sorted(p["name"] for p in row["players"] if p["kind"] == "human") == \
            sorted(seated)
        for name in seated:
            found = json.loads(await asyncio.to_thread(
                live_get, live, "/api/replays?player=" + urllib.parse.quote(name, safe="")))
            assert saved["id"] in [r["id"] for r in found["replays"]], name
        body = await asyncio.to_thread(live_get_bytes, live, f"/api/replays/{saved['id']}")
        header, _records = read_replay(body)
        assert header["room_name"] == want_room
        assert sorted(p["name"] for p in header["players"] if p["kind"] == "human") == \
            sorted(seated)
        for p in players:
            await p.close()
        await owner.close()
        live.call(lambda: asyncio.ensure_future(live.srv.lobby.remove(rid)))

    asyncio.run(asyncio.wait_for(main(), 120))
    assert live.errors.texts() == []
    assert live.srv.stats["rounds_not_saved"] == 0


def live_get_bytes(live: LiveServer, target: str) -> bytes:
    raw = live.http(f"GET {target} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode(), timeout=20)
    head, _, body = raw.partition(b"\r\n\r\n")
    assert head.split(b" ", 2)[1] == b"200", raw[:300]
    return body


def live_get(live: LiveServer, target: str) -> str:
    return live_get_bytes(live, target).decode()


# --- 2. malformed HTTP requests -------------------------------------------------------------


UPGRADE = ("GET /ws HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
           "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
           "Sec-WebSocket-Version: 13\r\n")


def test_malformed_requests_get_a_4xx_and_a_bounded_log(tmp_path) -> None:
    seen = ErrorLog(logging.DEBUG)
    for name in ("clothball", "websockets"):
        logging.getLogger(name).addHandler(seen)
    level = logging.getLogger("websockets").level
    logging.getLogger("websockets").setLevel(logging.WARNING)  # as clothball host sets it
    try:
        with live_server(tmp_path) as live:
            up = UPGRADE.format(port=live.srv.port)
            bad = [
                up + "Origin: http://a.example\r\nOrigin: http://b.example\r\n\r\n",
                up + f"Origin: http://127.0.0.1:{live.srv.port}\r\n"
                     f"Origin: http://127.0.0.1:{live.srv.port}\r\n\r\n",
                up.replace("Host: ", "Host: evil.example\r\nHost: ") + "\r\n",
                "GET /api/rooms HTTP/1.1\r\nHost: a\r\nHost: b\r\n\r\n",
                "GET /api/replays HTTP/1.1\r\nHost: a\r\nRange: bytes=0-1\r\nRange: bytes=2-3"
                "\r\n\r\n",
            ]
            for req in bad:
                answer = live.http(req.encode())
                assert answer.startswith(b"HTTP/1.1 400 "), (req, answer[:300])
                assert b"more than once" in answer
            latin = (up + "Origin: http://caf\xe9.example\r\n\r\n").encode("latin-1")
            answer = live.http(latin)
            assert answer.startswith(b"HTTP/1.1 400 ") and b"ASCII" in answer, answer[:300]
            # The bad-request lines only: other servers of the session may log their own.
            def bad_lines() -> list[str]:
                return [r.getMessage() for r in seen.records if "bad request" in r.getMessage()]

            n0 = len(bad_lines())
            for _ in range(300):
                assert live.http(bad[0].encode()).startswith(b"HTTP/1.1 400 ")
            # one address: its first bad request was logged, these 300 only counted
            assert len(bad_lines()) - n0 <= 1, bad_lines()
            assert not any(r.exc_info for r in seen.records)  # no tracebacks
            # the server still serves well-formed requests
            assert live.http(b"GET /healthz HTTP/1.1\r\nHost: a\r\n\r\n").endswith(b"ok\n")
        assert live.errors.texts() == []
        # stopping the server logs what was counted, once
        summary = [r.getMessage() for r in seen.records if "more bad requests" in r.getMessage()]
        assert len(summary) == 1 and "305 more" in summary[0], summary
    finally:
        for name in ("clothball", "websockets"):
            logging.getLogger(name).removeHandler(seen)
        logging.getLogger("websockets").setLevel(level)


def test_the_bad_request_log_is_bounded_across_addresses() -> None:
    from clothball.server.http import BadRequestLog

    seen = ErrorLog(logging.DEBUG)
    logging.getLogger("clothball").addHandler(seen)
    try:
        bad = BadRequestLog(window=3600, max_lines=5)
        for i in range(1000):
            bad.note(f"10.0.{i // 256}.{i % 256}", logging.WARNING, "x")
        assert len(seen.records) == 5
        bad.flush()
        lines = [r.getMessage() for r in seen.records[5:]]
        assert len(lines) <= 6 and any("other addresses" in s and "990 more" in s for s in lines)
    finally:
        logging.getLogger("clothball").removeHandler(seen)


# --- 3. index queries ------------------------------------------------------------------------


def fill(store: SqliteIndex, n: int, seed: int = 0) -> list[dict[str, Any]]:
    """``n`` rounds in a few rooms (one private), with seat names from a small pool."""
    rng = random.Random(seed)
    headers = []
    for i in range(n):
        room = rng.choice(["main", "r1", "r2", "secret"])
        seats = [{"seat": s, "kind": "human", "name": rng.choice(["ann", "bob", "cy", "dé"])}
                 for s in range(rng.randint(1, 4))]
        h = {"id": f"t{i:06d}-abc", "room_id": room, "room_name": room, "scene": "tiny",
             "round": i, "players": seats, "scores": [0, 0, 0, 0], "started_at": 0.0,
             "ended_at": float(rng.randint(0, n // 3)), "duration_s": 1.0}
        if room == "secret":
            h["access"] = access_key("secret", "pw")
        store.save(h, [])
        headers.append(h)
    return headers


def reference(headers: list[dict[str, Any]], room: str | None, player: str | None,
              code: str | None) -> list[str]:
    out = [h for h in headers
           if (h.get("access") is None or (room is not None and code is not None
                                           and h["access"] == access_key(room, code)))
           and (room is None or h["room_id"] == room)
           and (player is None or player in [p["name"] for p in h["players"]])]
    out.sort(key=lambda h: (-h["ended_at"], h["id"]))
    return [h["id"] for h in out]


def test_every_index_query_is_an_index_search_with_the_right_answer(tmp_path) -> None:
    store = SqliteIndex(tmp_path)
    headers = fill(store, 400)
    store._db.execute("ANALYZE")  # the plans must hold with statistics too
    for name, plan in store.query_plans().items():
        steps = [line.split(":", 1)[1] for line in plan]
        assert not any(s.startswith(("SCAN rounds", "SCAN round_players")) for s in steps), \
            (name, plan)
        # only the page itself (parent 0, at most LIMIT rows) may be sorted
        assert all(line.startswith("0:") for line in plan if "TEMP B-TREE" in line), \
            (name, plan)
    for room in (None, "main", "secret", "nowhere"):
        for player in (None, "ann", "dé", "nobody"):
            for code in (None, "pw", "wrong") if room else (None,):
                want = reference(headers, room, player, code)
                assert store.count(room, player=player, code=code) == len(want)
                for limit, offset in ((10, 0), (7, 3), (1000, 0), (5, len(want) - 2)):
                    got = [r["id"] for r in store.list(limit, max(0, offset), room,
                                                       player=player, code=code)]
                    assert got == want[max(0, offset):max(0, offset) + limit], \
                        (room, player, code, limit, offset)
    store.close()


def test_a_remembered_count_follows_every_write(tmp_path) -> None:
    store, other = SqliteIndex(tmp_path), SqliteIndex(tmp_path)  # two connections
    headers = fill(store, 30, seed=5)
    n, bob = store.count(), store.count(player="bob")
    for writer in (store, other):  # its own write, and another connection's
        h = {**headers[0], "id": f"new-{id(writer)}", "room_id": "main", "ended_at": 1e9}
        h.pop("access", None)
        writer.save(h, [])
        n, bob = n + 1, bob + ("bob" in [p["name"] for p in h["players"]])
        assert store.count() == n and store.count(player="bob") == bob
    other.close()
    store.close()


def test_an_older_index_gets_the_player_table_on_open(tmp_path) -> None:
    store = SqliteIndex(tmp_path)
    headers = fill(store, 60, seed=3)
    store.close()
    db = sqlite3.connect(tmp_path / "index.sqlite")  # as an index from before issue 22
    db.executescript("DROP TABLE round_players; DROP INDEX rounds_public; DROP INDEX rounds_room;"
                     "PRAGMA user_version = 0;")
    db.close()
    store = SqliteIndex(tmp_path)
    assert store.count(player="bob") == len(reference(headers, None, "bob", None)) > 0
    assert [r["id"] for r in store.list(1000, 0, "secret", player="cy", code="pw")] == \
        reference(headers, "secret", "cy", "pw")
    store.close()


def test_index_queries_run_on_their_own_threads_and_are_rate_limited(tmp_path) -> None:
    async def main() -> None:
        lim = Limits(index_rate=0.01, index_burst=3)
        async with server(tmp_path, limits=lim) as srv:
            assert srv.store is not None
            threads = []
            real = srv.store.count

            def count(*a: Any, **k: Any) -> int:
                threads.append(threading.current_thread().name)
                return real(*a, **k)

            srv.store.count = count  # type: ignore[method-assign]
            # Asked of this process: its index is watched, and the rate is per process (with
            # CLOTHBALL_TEST_WORKERS=2, the shared port would spread the queries over two).
            here = processes(srv)[0]
            for _ in range(3):
                assert (await http_json(here, "/api/replays"))["total"] == 0
            assert threads and all(t.startswith("replay-index") for t in threads), threads
            status, body, headers = await http_get(here, "/api/replays?player=x")
            assert status == 429 and b"replay queries a second" in body
            status, _, _ = await http_get(here, "/api/replays/nope")
            assert status == 429
            # the rest of the HTTP surface is not limited by it
            assert (await http_get(here, "/healthz"))[0] == 200
            assert (await http_get(here, "/api/rooms"))[0] == 200

    run(main())


# --- 4. private rooms on public endpoints ---------------------------------------------------


def test_public_endpoints_name_no_private_room(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path, settings=RoomSettings(**FAST)) as srv:
            owner = await NetClient.connect(srv.ws_url, name="owner")
            made = await owner.request("create_room", public=False)
            rid = made["room"]
            # known here: this process's room, or (two processes) in the directory it read
            await until(lambda: rid in srv.lobby.rooms or (
                srv.lobby.peers is not None and rid in srv.lobby.peers.rooms), 5)
            for proc in processes(srv):  # every process's endpoints
                for path in ("/api/stats", "/api/rooms", "/api/replays", "/"):
                    status, body, _ = await http_get(proc, path)
                    assert status == 200 and rid.encode() not in body, path
            assert "main" in (await service_stats(srv))["rooms"]
            await owner.close()

    run(main())


# --- 5. the origin policy ---------------------------------------------------------------------


def test_the_default_origin_policy_is_the_servers_own_pages(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path) as srv:
            port = public_port(srv)
            own = f"http://127.0.0.1:{port}"
            for origin in (own, None):  # its own page, and a client that is not a browser
                async with connect(srv.ws_url, origin=origin) as ws:
                    await ws.send(json.dumps(HELLO))
                    assert json.loads(await ws.recv())["type"] == "welcome"
            # a page redirected to a process's own port (--workers) is still its own page
            for proc in processes(srv):
                async with connect(proc.http_url.replace("http", "ws", 1) + "ws",
                                   origin=own) as ws:
                    await ws.send(json.dumps(HELLO))
                    assert json.loads(await ws.recv())["type"] == "welcome"
            for origin in ("https://elsewhere.example", "null", f"http://127.0.0.1:{port + 1}",
                           f"http://evil.example:{port}"):
                with pytest.raises(InvalidStatus) as e:
                    async with connect(srv.ws_url, origin=origin):
                        pass
                assert e.value.response.status_code == 403 and b"--origin" in \
                    e.value.response.body, origin
        async with server(tmp_path, origins=parse_origins(["*"])) as srv:
            async with connect(srv.ws_url, origin="https://elsewhere.example") as ws:
                await ws.send(json.dumps(HELLO))
                assert json.loads(await ws.recv())["type"] == "welcome"

    run(main())


def test_origin_values_are_checked() -> None:
    assert parse_origins(None) is None
    assert parse_origins(["https://a.example/", "*"]) == ("https://a.example", "*")
    for bad in ("a.example", "ftp://a.example", "http://a b"):
        with pytest.raises(ValueError, match="--origin"):
            parse_origins([bad])
