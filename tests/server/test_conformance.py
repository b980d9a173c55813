"""The conformance suite: every row of ``docs/protocol.md``'s tables (``protocol_doc.rows``:
each message, field, event, binary layout, error code, close code and HTTP path) checked
against a live server through real websocket clients written from the doc
(``conformance_client``), and the other way round: every message type, field, event and
error code the server sends or can send appears in those tables.

A doc row without a check here fails (``test_every_documented_row_has_a_check``), and so
does a check whose row is gone. Most checks read what one scripted session with the server
received (``Session``: a run of requests, rooms, a match, reconnects and each error case,
once per server kind: one process and two); a few need a server of their own (``Edge``: a
simulation that fails, a data directory that cannot be written, tiny room and keep-alive
limits).
"""

from __future__ import annotations

import asyncio
import contextlib
import gzip
import json
import math
import re
import struct
import time
import zlib
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from clothball.game.wire import protocol as P
from clothball.server.limits import Limits
from clothball.server.room import RoomSettings
from clothball.server.ws import WsEndpoint
from prometheus_client.parser import text_string_to_metric_families

from tests.server import protocol_doc as D
from tests.server import workers
from tests.server.conformance_client import HELLO, Transcript, Wire, raw_ws_close_code
from tests.server.conftest import FAST, TINY, http_get_url, live_server, run
from tests.server.unstable import unstable_scene

# The edge server's room is unstable on purpose (its simulation must fail).
pytestmark = pytest.mark.filterwarnings(
    "ignore::clothball.game.sim.cloth.UnstableSceneWarning")

ROWS = {r.id: r for r in D.rows()}
TABLES = D.tables()


def _doc_fields(table: str, key: str) -> set[str]:
    return {r.field for r in ROWS.values() if r.table == table and r.key == key and r.field}


def _table_keys(table: str) -> list[str]:
    return [r.key for r in ROWS.values() if r.table == table and r.field is None]


# --- the binary layouts, read from the doc's tables -----------------------------------------

_CODES = {"u8": "B", "u16": "H", "u32": "I", "i64": "q", "f32": "f", "f64": "d"}


def layout(table: str) -> dict[int, str]:
    """offset -> struct format (little-endian) of each row of a binary table."""
    out = {}
    for row in TABLES[table].rows:
        t = row["type"].replace(" ", "")
        if t == "...":
            continue
        count, _, base = t.rpartition("×")
        out[int(row["offset"])] = "<" + (count or "") + _CODES[base]
    return out


def read(data: bytes, table: str, offset: int) -> Any:
    v = struct.unpack_from(layout(table)[offset], data, offset)
    return v[0] if len(v) == 1 else np.array(v, dtype=np.float64)


def header_types() -> dict[int, str]:
    values = next(r["values"] for r in TABLES["header"].rows if r["field"] == "type")
    return {int(n): name for n, name in re.findall(r"(\d+) ([A-Z]+)", values)}


def decode_mesh_payload(data: bytes) -> np.ndarray:
    """The MESH payload decoded by the doc's words: bit 0 zlib; version 2: byte planes, bit
    1 zigzag 2-D residuals (unmapped, summed down the columns, then along the rows);
    version 1: uint16 per axis, bit 1 row deltas (a cumulative sum along each row);
    p = min + q (max - min) / 65535."""
    n = read(data, "mesh", 24)
    flags = read(data, "header", 2)
    payload = data[116:]
    if flags & 1:
        payload = zlib.decompress(payload)
    if data[1] == 2:
        b = np.frombuffer(payload, dtype=np.uint8).astype(np.uint16)
        q = np.stack([b[2 * a * n * n:(2 * a + 1) * n * n]
                      | (b[(2 * a + 1) * n * n:(2 * a + 2) * n * n] << 8) for a in range(3)],
                     axis=-1).reshape(n, n, 3)
        if flags & 2:
            r = (q >> 1) ^ (np.uint16(0) - (q & 1))
            q = np.cumsum(np.cumsum(r, axis=0, dtype=np.uint16), axis=1, dtype=np.uint16)
    else:
        q = np.frombuffer(payload, dtype="<u2").reshape(n, n, 3)
        if flags & 2:
            q = np.cumsum(q, axis=1, dtype=np.uint16)
    lo, hi = read(data, "mesh", 28), read(data, "mesh", 40)
    return lo + q.astype(np.float64) * (hi - lo) / 65535


# --- the scripted session ----------------------------------------------------------------------


@dataclass
class Session:
    mode: int  # server processes: 1 or 2
    http_url: str
    t: Transcript = field(default_factory=Transcript)
    got: dict[str, Any] = field(default_factory=dict)


# Requests refused for one field (row id -> the request and the error code it gets). Sent
# from the lobby, or from the room's host in its room (IN_ROOM).
BAD_FIELDS: dict[str, tuple[dict[str, Any], str]] = {
    "requests:hello.name": ({"type": "hello", "version": 1, "name": "x" * 33}, "bad_message"),
    "requests:create_room.name": ({"type": "create_room", "name": "x" * 49}, "bad_message"),
    "requests:create_room.scene": ({"type": "create_room", "scene": "nope"}, "bad_message"),
    "requests:create_room.public": ({"type": "create_room", "public": "yes"}, "bad_message"),
    "requests:create_room.first_to": ({"type": "create_room", "first_to": 100}, "bad_message"),
    "requests:create_room.countdown": ({"type": "create_room", "countdown": 11},
                                       "bad_message"),
    "requests:create_room.reset_offset": ({"type": "create_room", "reset_offset": 0.3},
                                          "bad_message"),
    "requests:create_room.reset_speed": ({"type": "create_room", "reset_speed": 5.5},
                                         "bad_message"),
    "requests:create_room.bots_allowed": ({"type": "create_room", "bots_allowed": 1},
                                          "bad_message"),
    "requests:create_room.unguarded": ({"type": "create_room", "unguarded": "no"},
                                       "bad_message"),
    "requests:create_room.bot_difficulty": ({"type": "create_room", "bot_difficulty": 1.5},
                                            "bad_message"),
    "requests:create_room.grace": ({"type": "create_room", "grace": 0.4}, "bad_message"),
    "requests:create_room.autoplay": ({"type": "create_room", "autoplay": "on"},
                                      "bad_message"),
    "requests:create_room.restart_delay": ({"type": "create_room", "restart_delay": 61},
                                           "bad_message"),
    "requests:create_room.record_cap_s": ({"type": "create_room", "record_cap_s": 0.5},
                                          "bad_message"),
    "requests:join.room": ({"type": "join", "role": "spectator"}, "bad_message"),
    "requests:join.role": ({"type": "join", "room": "main", "role": "king"}, "bad_message"),
    "requests:join.seat": ({"type": "join", "room": "main", "role": "player", "seat": 7},
                           "bad_seat"),
    "requests:join.token": ({"type": "join", "token": "main.not-a-token"}, "bad_token"),
    "requests:join.corner_rate": ({"type": "join", "room": "main", "role": "player",
                                   "corner_rate": 0}, "bad_message"),
    "requests:join.mesh": ({"type": "join", "room": "main", "role": "spectator",
                            "mesh": "no"}, "bad_message"),
    "requests:ready.ready": ({"type": "ready", "ready": "yes"}, "bad_message"),
    "requests:add_bot.seat": ({"type": "add_bot", "seat": 9}, "bad_seat"),
    "requests:add_bot.difficulty": ({"type": "add_bot", "difficulty": 2}, "bad_message"),
    "requests:remove_bot.seat": ({"type": "remove_bot", "seat": 9}, "bad_seat"),
    "requests:ping.t": ({"type": "ping", "t": "now"}, "bad_message"),
}
IN_ROOM = ("ready", "add_bot", "remove_bot")

# The room the host makes: every create_room field set, none to its default.
# (reset_speed: a round and its 1 s tail outlast the 1 s record_cap_s however loaded the
# machine, so that the replay is cut.)
CONF_ROOM = dict(name="conformance", scene="tiny", public=False, first_to=1, countdown=1,
                 reset_offset=0.0, reset_speed=2.0, bots_allowed=True, unguarded=False,
                 bot_difficulty=0.3, grace=2.0, autoplay=False, restart_delay=0,
                 record_cap_s=1)


async def scenario(s: Session, ws_url: str) -> None:
    t, got = s.t, s.got
    wires: list[Wire] = []

    async def wire(hello: dict[str, Any] | None = None, url: str = ws_url) -> Wire:
        w = Wire(t, url)
        wires.append(w)
        await w.open(hello)
        return w

    # -- with an engine and a gateway: a hello that joins, which a process of several
    # processes once answered with a redirect, is answered where the client connected
    # (the rooms made below, through the gateway too, are answered there as well)
    if s.mode == 2:
        w2 = await wire({"role": "spectator", "room": "main"})
        got["direct_hello_join"] = w2.msgs[0]
        await w2.close()

    # -- the lobby
    lob = await wire({"name": "Zoe\u0308", "id": "h-1"})  # NFD: normalised to NFC
    got["welcome"] = lob.msgs[0]
    got["list_rooms"] = await lob.request({"type": "list_rooms"})
    got["pong"] = await lob.request({"type": "ping", "t": 1.5})
    got["pong_no_t"] = await lob.request({"type": "ping"})
    got["state_lobby"] = await lob.request({"type": "state"})
    got["leave_lobby"] = await lob.request({"type": "leave"})
    got["second_hello"] = await lob.request({"type": "hello", "version": 1})
    for rid, (msg, _code) in BAD_FIELDS.items():
        if msg["type"] not in IN_ROOM:
            if msg["type"] == "hello":
                w = Wire(t, ws_url)
                got[rid] = await w.open({k: v for k, v in msg.items() if k != "type"})
                got[rid + "/close"] = await w.closed()
            else:
                got[rid] = await lob.request(msg)
            await asyncio.sleep(0.25)  # under the error replies' rate (a fixed wait)
    got["hello_role_king"] = await _refused_hello(t, ws_url, {"role": "king"})
    got["hello_no_version"] = await _refused_hello(t, ws_url, {"version": None})
    got["hello_version_2"] = await _refused_hello(t, ws_url, {"version": 2})
    got["hello_role_spectator"] = await (await wire({"role": "spectator",
                                                     "room": "main"})).next(
        lambda m: m["type"] == "joined")

    # -- a room with every setting, its host seated, a spectator, a second player
    host = await wire({"name": "host"})
    got["created"] = created = await host.request({"type": "create_room", **CONF_ROOM})
    rid, code = created["room"], created["code"]
    got["listed_private"] = await host.request({"type": "list_rooms"})
    got["bad_code"] = await host.request({"type": "join", "room": rid, "role": "spectator",
                                          "code": "wrong"})
    got["joined_host"] = await host.request({"type": "join", "room": rid, "role": "player",
                                             "seat": 0, "code": code, "corner_rate": 50,
                                             "mesh": True})
    spec = await wire({"role": "spectator", "room": rid, "code": code, "name": "spec",
                       "mesh": False})
    got["joined_spec"] = spec.joined
    got["state"] = await host.request({"type": "state"})
    for rowid, (msg, _code) in BAD_FIELDS.items():
        if msg["type"] in IN_ROOM:
            got[rowid] = await host.request(msg)
            await asyncio.sleep(0.25)  # under the error replies' rate (a fixed wait)
    got["add_bot"] = await host.request({"type": "add_bot", "seat": 1, "difficulty": 0.5})
    got["remove_bot"] = await host.request({"type": "remove_bot", "seat": 1})
    got["remove_no_bot"] = await host.request({"type": "remove_bot", "seat": 1})
    await host.request({"type": "add_bot", "seat": 1})
    # a player takes the bot's seat; drops; resumes by token; is replaced by a resume
    p2 = await wire({"role": "player", "room": rid, "code": code, "seat": 1, "name": "p2",
                     "mesh": False, "corner_rate": 5})
    got["joined_p2"] = p2.joined
    assert p2.joined is not None and p2.joined["type"] == "joined", p2.joined
    token = p2.joined["token"]
    await p2.close()
    got["held"] = await spec.event("seat", seat=1, held_for=CONF_ROOM["grace"])
    p2b = await wire({"token": token, "mesh": False, "corner_rate": 5})
    got["resumed"] = await spec.event("seat", seat=1, resumed=True)
    got["joined_resumed"] = p2b.joined
    p2c = await wire({"token": token, "mesh": False, "corner_rate": 5})
    got["replaced_close"] = await p2b.closed()
    await p2c.close()
    got["grace_over"] = await spec.event("seat", seat=1, reason="grace_over")

    # the host's hand: a HIP it sends comes back in its CORNER and in the MESH
    centre = np.array(got["joined_host"]["reach"]["centre"])
    hip_pos = centre + np.array([0.01, 0.02, -0.01])
    hip = struct.pack("<BBHId3f", 1, 1, 0, 7, 123.25, *hip_pos)
    mark = len(host.binary)
    await host.send(hip)
    got["hip"] = (hip_pos.astype(np.float32).astype(np.float64), 7, 123.25)

    async def corner_echo() -> bytes:
        while True:
            for b in host.binary[mark:]:
                if b[0] == 2 and struct.unpack_from("<I", b, 92)[0] == 7:
                    return b
            await asyncio.sleep(0.01)

    got["corner"] = await asyncio.wait_for(corner_echo(), 15)
    m0 = len(host.binary)
    frame = struct.unpack_from("<q", got["corner"], 16)[0]

    async def mesh_after() -> bytes:  # of a frame the HIP was applied in
        while True:
            for b in host.binary[m0:]:
                if b[0] == 3 and struct.unpack_from("<q", b, 16)[0] >= frame:
                    return b
            await asyncio.sleep(0.01)

    got["mesh"] = await asyncio.wait_for(mesh_after(), 15)
    t0, c0 = time.monotonic(), sum(1 for b in host.binary[m0:] if b[0] == 2)
    await asyncio.sleep(1.0)  # (the window the rate's upper bound is counted over)

    def corners() -> int:
        return sum(1 for b in host.binary[m0:] if b[0] == 2) - c0

    while corners() == 0:  # and at least one CORNER in it, however slow the machine
        assert time.monotonic() - t0 < 30, "no CORNER in 30 s"
        await asyncio.sleep(0.05)
    got["corner_rate"] = (corners(), time.monotonic() - t0)
    got["pong_in_room"] = await host.request({"type": "ping"})
    for name, data in [("hip_out_of_range", struct.pack("<BBHId3f", 1, 1, 0, 8, 0.0,
                                                        *(centre + 5.0))),
                       ("hip_flags", struct.pack("<BBHId3f", 1, 1, 1, 9, 0.0, *centre)),
                       ("hip_version", struct.pack("<BBHId3f", 1, 2, 0, 9, 0.0, *centre)),
                       ("hip_short", b"\x01\x01\x00")]:
        mark = len(host.msgs)
        await host.send(data)
        got[name] = await host.next(lambda m: m["type"] == "error", since=mark)
        await asyncio.sleep(0.25)  # under the error replies' rate (a fixed wait)
    mark = len(spec.msgs)
    await spec.send(hip)
    got["hip_spectator"] = await spec.next(lambda m: m["type"] == "error", since=mark)

    # the match: the host gets ready, bots take the empty seats (backfill), one round
    got["ready"] = await host.request({"type": "ready", "ready": True})
    got["start_running"] = await host.request({"type": "start"})
    got["match_start"] = await spec.event("match_start")
    got["round_start"] = await spec.event("round_start")
    got["score"] = await spec.event("score")
    got["match_end"] = await spec.event("match_end")
    got["replay_saved"] = saved = await spec.event("replay_saved")
    got["replay_file"] = http_get_url(f"{s.http_url}api/replays/{saved['id']}?code={code}")
    got["replay_no_code"] = http_get_url(f"{s.http_url}api/replays/{saved['id']}")
    got["replays_room"] = http_get_url(f"{s.http_url}api/replays?room={rid}&code={code}")
    got["replays_room_no_code"] = http_get_url(f"{s.http_url}api/replays?room={rid}")
    got["replays_player"] = http_get_url(f"{s.http_url}api/replays?player=host&room={rid}"
                                         f"&code={code}")
    got["replays_bad_limit"] = http_get_url(f"{s.http_url}api/replays?limit=many")
    got["spec_binary"] = len(spec.binary)  # mesh: false, and no seat: nothing binary
    got["left"] = await host.request({"type": "leave"})
    got["left_event"] = await spec.event("seat", seat=0, reason="left")

    # -- a room that cannot start: no bots, no unguarded edges
    h2 = await wire({"name": "h2"})
    made = await h2.request({"type": "create_room", "scene": "tiny", "bots_allowed": False,
                             "unguarded": False})
    await h2.request({"type": "join", "room": made["room"], "role": "player", "seat": 0,
                      "mesh": False, "corner_rate": 5})
    got["cannot_start_error"] = await h2.request({"type": "start"})
    got["add_bot_no_bots"] = await h2.request({"type": "add_bot"})
    await h2.request({"type": "ready"})
    got["cannot_start_event"] = await h2.event("cannot_start")
    await h2.close()

    # -- unguarded edges: a match starts with one player; it leaves: the match is aborted
    h3 = await wire({"name": "h3"})
    made = await h3.request({"type": "create_room", "scene": "tiny", "bots_allowed": False,
                             "unguarded": True, "countdown": 3})
    got["unguarded_room"] = made
    await h3.request({"type": "join", "room": made["room"], "role": "player", "seat": 2,
                      "mesh": False, "corner_rate": 5})
    s3 = await wire({"role": "spectator", "room": made["room"], "mesh": False})
    got["start_unguarded"] = await h3.request({"type": "start"})
    got["unguarded_match_start"] = await s3.event("match_start")
    got["countdown"] = await s3.event("countdown")
    await h3.request({"type": "leave"})
    got["match_abort"] = await s3.event("match_abort")
    await s3.close()

    # -- autoplay: bots alone start (and, with no delay, restart) matches by themselves
    h4 = await wire({"name": "h4"})
    made = await h4.request({"type": "create_room", "scene": "tiny", "autoplay": True,
                             "restart_delay": 0, "first_to": 1, "countdown": 0,
                             "reset_speed": 3.0})
    await h4.request({"type": "join", "room": made["room"], "role": "spectator",
                      "mesh": False})
    await h4.request({"type": "add_bot", "seat": 0})  # autoplay starts a match: with...
    await h4.request({"type": "add_bot", "seat": 1})  # ...this one too, rounds are scored
    await h4.event("match_end", timeout=60)
    got["autoplay_restart"] = await h4.event("match_start", timeout=60,
                                             since=len(h4.msgs) - 1)
    await h4.close()

    # -- rooms per address: more rooms than this address may hold
    filler = await wire()
    for _ in range(10):
        got["too_many_rooms"] = await filler.request({"type": "create_room", "scene": "tiny",
                                                      "public": False})
        if got["too_many_rooms"]["type"] == "error":
            break

    # -- the main room full of players; one more is refused
    players = [await wire({"role": "player", "room": "main", "seat": i, "mesh": False,
                           "corner_rate": 1, "name": f"m{i}"}) for i in range(4)]
    got["joined_main"] = [p.joined for p in players]
    got["room_full"] = await (await wire()).request({"type": "join", "room": "main",
                                                     "role": "player"})
    for p in players:
        await p.close()

    # -- the other errors, each on a connection of its own
    for name, data in [("bad_json", "{oops"), ("bad_json_nan", '{"type": "ping", "t": NaN}'),
                       ("unknown_type", '{"type": "fly"}'),
                       ("too_big", json.dumps({"type": "ping", "pad": "x" * 5000})),
                       ("unknown_room", json.dumps({"type": "join", "room": "nope"})),
                       ("bad_id", json.dumps({"type": "ping", "id": 1.5}))]:
        w = await wire()
        mark = len(w.msgs)
        await w.send(data)
        got[name] = await w.next(lambda m: m["type"] == "error", since=mark)
        await w.close()
    w = await wire()
    for _ in range(80):  # over the control messages' burst: some dropped
        await w.send('{"type": "ping"}')
    got["rate_limited"] = await w.next(lambda m: m.get("code") == "rate_limited")
    await asyncio.sleep(1.5)  # the error replies' bucket refills: the next says suppressed
    await w.send('{"type": "fly"}')
    got["suppressed"] = await w.next(lambda m: m.get("code") == "unknown_type"
                                     and "suppressed" in m)
    await w.close()
    w = await wire()
    await w.send(b"\0" * 70000)
    got["close_1009"] = await w.closed()
    w = Wire(t, ws_url)
    await w.open({"version": 2})
    got["close_bad_hello"] = await w.closed()

    for w in wires:
        await w.close()


async def _refused_hello(t: Transcript, url: str, extra: dict[str, Any]) -> tuple[dict, int]:
    w = Wire(t, url)
    hello = {k: v for k, v in {**HELLO, **extra}.items() if v is not None}
    await w._connect(url)
    await w.send(json.dumps(hello))
    err = await w.next(lambda m: m["type"] == "error")
    return err, await w.closed()


# --- the server of its own for the rows a normal one cannot show ----------------------------


@dataclass
class Edge:
    t: Transcript = field(default_factory=Transcript)
    got: dict[str, Any] = field(default_factory=dict)


async def edge_scenario(tmp: Path) -> Edge:
    e = Edge()
    (tmp / "a-file").write_text("not a directory")
    data = tmp / "a-file" / "data"  # recording is off: every round's replay_failed
    # A keep-alive short enough to see a client that never answers closed (1011), long
    # enough that the suite's own clients (in this loop, with the server) always answer.
    limits = Limits(max_rooms=3, ping_interval=1.0, ping_timeout=5.0,
                    admit_lateness_ms=0.0)
    settings = RoomSettings(autoplay=True, **{**FAST, "first_to": 99})
    async with _edge_server(data, limits, settings) as srv:
        url = srv.ws_url
        spec = Wire(e.t, url)
        await spec.open({"role": "spectator", "room": "main", "mesh": False})
        e.got["replay_failed"] = await spec.event("replay_failed", timeout=60)
        owner = Wire(e.t, url)
        await owner.open()
        made = await owner.request({"type": "create_room", "scene": "unstable"})
        player = Wire(e.t, url)
        await player.open({"role": "player", "room": made["room"], "mesh": False,
                           "corner_rate": 5})
        e.got["room_stopped_event"] = await player.event("room_stopped", timeout=60)
        e.got["room_stopped_error"] = await player.next(
            lambda m: m["type"] == "error" and m["code"] == "room_stopped")
        for _ in range(5):
            e.got["server_busy"] = await owner.request({"type": "create_room",
                                                        "scene": "tiny"})
            if e.got["server_busy"]["type"] == "error":
                break
        e.got["close_1011"] = await asyncio.to_thread(
            raw_ws_close_code, "127.0.0.1", srv.port, b'{"type":"hello","version":1}', 60.0)
        for w in (spec, owner, player):
            await w.close()
    return e


@contextlib.asynccontextmanager
async def _edge_server(data: Path, limits: Limits, settings: RoomSettings
                       ) -> AsyncIterator[Any]:
    """One process, whatever the session's kind: what it shows is the same in both."""
    from clothball.server.app import GameServer, ServerConfig

    srv = GameServer(ServerConfig(data, scenes={"tiny": TINY, "unstable": unstable_scene()},
                                  backend="cpu", host="127.0.0.1", port=0, bots=4,
                                  room_settings=settings, limits=limits))
    await srv.start()
    try:
        yield srv
    finally:
        await srv.stop()


# --- fixtures ----------------------------------------------------------------------------------

MODES = [1, 2] if workers.WORKERS == 1 else [workers.WORKERS]


@pytest.fixture(scope="module", params=MODES, ids=[f"{n}proc{'s' * (n > 1)}" for n in MODES])
def session(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
            ) -> Iterator[Session]:
    mode = request.param
    with workers.using(mode), live_server(tmp_path_factory.mktemp(f"conf{mode}")) as ls:
        s = Session(mode, ls.srv.http_url.rstrip("/") + "/")
        run(scenario(s, ls.srv.ws_url), timeout=300)
        s.got["stats"] = [json.loads(http_get_url(p.http_url + "api/stats")[1])
                          for p in workers.processes(ls.srv)]
        s.got["metrics"] = [http_get_url(p.http_url + "metrics")
                            for p in workers.processes(ls.srv)]
        s.got["errors_logged"] = ls.errors.texts()
        yield s


@pytest.fixture(scope="module")
def edge(tmp_path_factory: pytest.TempPathFactory) -> Edge:
    return run(edge_scenario(tmp_path_factory.mktemp("edge")), timeout=240)


# --- the checks, by row ----------------------------------------------------------------------

Check = Callable[..., None]
CHECKS: dict[str, Check] = {}  # row id (or "TABLE:*": every row of a table) -> check


def check(*ids: str) -> Callable[[Check], Check]:
    def register(fn: Check) -> Check:
        for i in ids:
            assert i not in CHECKS, f"two checks for {i}"
            CHECKS[i] = fn
        return fn

    return register


def check_for(row_id: str) -> Check | None:
    if row_id in CHECKS:
        return CHECKS[row_id]
    return CHECKS.get(row_id.split(":")[0] + ":*")


def err(msg: dict[str, Any], code: str) -> None:
    assert msg["type"] == "error" and msg["code"] == code and msg["message"], (code, msg)


# seats ----------------------------------------------------------------------------------------


@check("seats:*")
def _seat(s: Session, row: D.Row) -> None:
    seat = int(row.key)
    edge_name = row.cells["edge"].strip()
    c0, c1 = (int(c) for c in re.findall(r"\d", row.cells["corners"]))
    axis, sign = re.match(r"([xz]) = ([+−])size/2", row.cells["at rest"]).groups()
    joined = s.got["joined_main"][seat]
    assert joined["seat"] == seat and joined["edge"] == seat
    assert joined["edge_name"] == edge_name == joined["geometry"]["edges"][seat]
    assert joined["state"]["seats"][seat]["edge"] == edge_name
    g = joined["geometry"]
    a = np.array(g["anchors"])
    k = "xyz".index(axis)
    want = (1 if sign == "+" else -1) * g["size"] / 2
    assert a[c0][k] == pytest.approx(want) and a[c1][k] == pytest.approx(want)
    assert joined["reach"]["centre"] == g["anchors"][seat]  # seat s holds corner s


# requests -------------------------------------------------------------------------------------


def _bad_field(s: Session, row: D.Row) -> None:
    """A field whose only check is its refusal (registered below, after the others)."""
    err(s.got[row.id], BAD_FIELDS[row.id][1])
    if row.key == "hello":
        assert s.got[row.id + "/close"] == 1008


@check("requests:hello", "replies:welcome")
def _hello(s: Session, row: D.Row) -> None:
    w = s.got["welcome"]
    assert w["type"] == "welcome" and w["re"] == "h-1"
    assert w["name"] == "Zo\u00eb"  # NFC
    err(s.got["second_hello"], "not_allowed")


@check("requests:hello.version")
def _hello_version(s: Session, row: D.Row) -> None:
    assert s.got["welcome"]["version"] == 1
    e, code = s.got["hello_no_version"]
    err(e, "bad_message")
    assert code == 1008
    e, code = s.got["hello_version_2"]
    err(e, "bad_version")
    assert code == 1008


@check("requests:hello.role")
def _hello_role(s: Session, row: D.Row) -> None:
    e, code = s.got["hello_role_king"]
    err(e, "bad_message")
    assert code == 1008
    assert s.got["hello_role_spectator"]["role"] == "spectator"


@check("requests:list_rooms", "replies:rooms")
def _list_rooms(s: Session, row: D.Row) -> None:
    ids = [r["id"] for r in s.got["list_rooms"]["rooms"]]
    assert "main" in ids
    # private rooms are not listed
    assert s.got["created"]["room"] not in [r["id"] for r in s.got["listed_private"]["rooms"]]
    # a lobby connection is also sent the list by itself (here: as rooms were made)
    assert len([m for m in s.t.of("rooms") if "re" not in m]) >= 1


@check("requests:create_room", "replies:room_created")
def _create_room(s: Session, row: D.Row) -> None:
    c = s.got["created"]
    assert c["type"] == "room_created" and isinstance(c["room"], str)
    assert isinstance(c["code"], str) and c["code"]  # private: its code
    assert s.got["unguarded_room"]["code"] is None  # public: null


def _state(s: Session) -> dict[str, Any]:
    return s.got["created"]["state"]


@check("requests:create_room.name")
def _cr_name(s: Session, row: D.Row) -> None:
    assert _state(s)["name"] == CONF_ROOM["name"]
    err(s.got[row.id], "bad_message")


@check("requests:create_room.scene")
def _cr_scene(s: Session, row: D.Row) -> None:
    assert _state(s)["scene"] == "tiny" and "tiny" in s.got["welcome"]["scenes"]
    err(s.got[row.id], "bad_message")


@check("requests:create_room.public")
def _cr_public(s: Session, row: D.Row) -> None:
    assert _state(s)["public"] is False
    err(s.got[row.id], "bad_message")


@check("requests:create_room.first_to")
def _cr_first_to(s: Session, row: D.Row) -> None:
    assert _state(s)["first_to"] == 1 and s.got["match_start"]["first_to"] == 1
    assert max(s.got["match_end"]["scores"]) == 1  # one round decides it
    err(s.got[row.id], "bad_message")


@check("requests:create_room.countdown")
def _cr_countdown(s: Session, row: D.Row) -> None:
    # countdown 3 in the unguarded room: its first event says 3 whole seconds
    assert s.got["countdown"]["seconds"] == 3
    err(s.got[row.id], "bad_message")


@check("requests:create_room.reset_offset")
def _cr_reset_offset(s: Session, row: D.Row) -> None:
    start = TINY["ball"]["position"]
    assert s.got["round_start"]["ball"] == pytest.approx(start, abs=1e-12)  # offset 0
    err(s.got[row.id], "bad_message")


@check("requests:create_room.reset_speed")
def _cr_reset_speed(s: Session, row: D.Row) -> None:
    v = np.array(s.got["round_start"]["ball_velocity"]) - np.array(TINY["ball"]["velocity"])
    assert math.hypot(v[0], v[2]) == pytest.approx(CONF_ROOM["reset_speed"])
    assert v[1] == pytest.approx(0.0)
    err(s.got[row.id], "bad_message")


@check("requests:create_room.bots_allowed")
def _cr_bots_allowed(s: Session, row: D.Row) -> None:
    assert _state(s)["bots_allowed"] is True and s.got["add_bot"]["type"] == "ok"
    err(s.got["add_bot_no_bots"], "not_allowed")
    err(s.got[row.id], "bad_message")


@check("requests:create_room.unguarded")
def _cr_unguarded(s: Session, row: D.Row) -> None:
    assert s.got["unguarded_room"]["state"]["unguarded"] is True
    assert s.got["start_unguarded"]["type"] == "ok"
    assert s.got["unguarded_match_start"]["seats"] == [2]  # the one seated player
    err(s.got[row.id], "bad_message")


@check("requests:create_room.bot_difficulty")
def _cr_bot_difficulty(s: Session, row: D.Row) -> None:
    # accepted in range (how a bot plays is not visible on the wire), refused outside
    assert s.got["created"]["type"] == "room_created"
    err(s.got[row.id], "bad_message")


@check("requests:create_room.grace")
def _cr_grace(s: Session, row: D.Row) -> None:
    assert s.got["held"]["held_for"] == CONF_ROOM["grace"]
    err(s.got[row.id], "bad_message")


@check("requests:create_room.autoplay", "requests:create_room.restart_delay")
def _cr_autoplay(s: Session, row: D.Row) -> None:
    # nobody asked: the bots' match started, ended and (no delay) started again, with the
    # seats as they are (no bot added)
    assert s.got["autoplay_restart"]["event"] == "match_start"
    assert s.got["autoplay_restart"]["seats"] == [0, 1]
    err(s.got[row.id], "bad_message")


@check("requests:create_room.record_cap_s")
def _cr_record_cap(s: Session, row: D.Row) -> None:
    # a round and its 1 s tail are longer than the 1 s cap: the replay says it was cut
    status, body, _ = s.got["replay_file"]
    header = _replay_header(body)
    assert isinstance(header["cut"], str) and "cap" in header["cut"]
    assert header["duration_s"] <= CONF_ROOM["record_cap_s"] + 0.05
    err(s.got[row.id], "bad_message")


def _replay_header(body: bytes) -> dict[str, Any]:
    raw = gzip.decompress(body)
    assert raw[:16] == b"CLOTHBALL-REPLAY"
    version, hlen = struct.unpack_from("<II", raw, 16)
    assert version == 1
    return json.loads(raw[24:24 + hlen])


@check("requests:join", "replies:joined", "requests:join.code")
def _join(s: Session, row: D.Row) -> None:
    j = s.got["joined_host"]
    assert j["type"] == "joined" and j["room"] == s.got["created"]["room"]
    assert j["code"] == s.got["created"]["code"]
    err(s.got["bad_code"], "bad_code")


@check("requests:join.room")
def _join_room(s: Session, row: D.Row) -> None:
    assert s.got["joined_spec"]["room"] == s.got["created"]["room"]
    err(s.got[row.id], "bad_message")
    err(s.got["unknown_room"], "unknown_room")


@check("requests:join.role")
def _join_role(s: Session, row: D.Row) -> None:
    assert s.got["joined_host"]["role"] == "player"
    assert s.got["joined_spec"]["role"] == "spectator"
    spec = set(s.got["joined_spec"]) - {"re"}  # (a hello's join: re is the hello's id)
    assert spec == {"type", "room", "role", "geometry", "state"}
    err(s.got[row.id], "bad_message")


@check("requests:join.seat")
def _join_seat(s: Session, row: D.Row) -> None:
    assert s.got["joined_p2"]["seat"] == 1 and s.got["joined_host"]["seat"] == 0
    err(s.got[row.id], "bad_seat")


@check("requests:join.token")
def _join_token(s: Session, row: D.Row) -> None:
    r = s.got["joined_resumed"]
    assert r["seat"] == 1 and r["token"] == s.got["joined_p2"]["token"]
    assert r["token"].startswith(s.got["created"]["room"] + ".")
    err(s.got[row.id], "bad_token")


@check("requests:join.corner_rate")
def _join_corner_rate(s: Session, row: D.Row) -> None:
    n, dt = s.got["corner_rate"]
    assert 0 < n <= 50 * dt + 2  # at most corner_rate a second (an upper bound: no timing)
    err(s.got[row.id], "bad_message")


@check("requests:join.mesh")
def _join_mesh(s: Session, row: D.Row) -> None:
    assert s.got["mesh"][0] == 3  # the host asked for MESH; the spectator did not
    assert s.got["spec_binary"] == 0
    err(s.got[row.id], "bad_message")


@check("requests:leave", "replies:left")
def _leave(s: Session, row: D.Row) -> None:
    assert s.got["left"]["room"] == s.got["created"]["room"]
    assert s.got["left_event"]["kind"] == "empty"  # freed at once
    err(s.got["leave_lobby"], "not_allowed")


@check("requests:ready", "requests:ready.ready", "replies:ok")
def _ready(s: Session, row: D.Row) -> None:
    assert s.got["ready"] == {"type": "ok", "re": s.got["ready"]["re"]}
    assert s.got["match_start"]["seats"] == [0, 1, 2, 3]  # ready: it started
    if row.id == "requests:ready.ready":
        err(s.got[row.id], "bad_message")


@check("requests:start")
def _start(s: Session, row: D.Row) -> None:
    assert s.got["start_unguarded"]["type"] == "ok"
    err(s.got["start_running"], "illegal_move")


@check("requests:add_bot", "requests:add_bot.difficulty")
def _add_bot(s: Session, row: D.Row) -> None:
    assert s.got["add_bot"]["type"] == "ok"
    assert any(e["seat"] == 1 and e.get("reason") == "added" for e in s.t.events("seat"))
    if row.field:
        err(s.got[row.id], "bad_message")


@check("requests:add_bot.seat", "requests:remove_bot.seat")
def _bot_seat(s: Session, row: D.Row) -> None:
    err(s.got[row.id], "bad_seat")
    assert "0..3" in s.got[row.id]["message"]


@check("requests:remove_bot")
def _remove_bot(s: Session, row: D.Row) -> None:
    assert s.got["remove_bot"]["type"] == "ok"
    assert any(e["seat"] == 1 and e.get("reason") == "bot_removed"
               for e in s.t.events("seat"))
    err(s.got["remove_no_bot"], "bad_seat")


@check("requests:state")
def _state_req(s: Session, row: D.Row) -> None:
    st = s.got["state"]
    assert st["type"] == "room" and st["id"] == s.got["created"]["room"]
    err(s.got["state_lobby"], "not_allowed")


@check("requests:ping", "requests:ping.t", "replies:pong")
def _ping(s: Session, row: D.Row) -> None:
    assert s.got["pong"]["t"] == 1.5 and s.got["pong_no_t"]["t"] is None
    assert s.got["pong"]["server_time"] > 0
    if row.field:
        err(s.got[row.id], "bad_message")


# replies: each documented field is sent (and nothing else: test_nothing_undocumented_is_sent)


NEVER_IN_ONE_HOST = {"redirect"}  # sent only between hosts of a cluster (test_cluster)


@check("replies:*")
def _reply_field(s: Session, row: D.Row) -> None:
    msgs = s.t.of(row.key)
    if row.key in NEVER_IN_ONE_HOST:
        assert not msgs, f"one host ({s.mode} processes) sent {row.key}"
        return
    assert msgs, f"no {row.key} message was received"
    if row.field is not None:
        assert any(row.field in m for m in msgs), f"no {row.key} carried {row.field}"


@check("replies:redirect")
def _redirect(s: Session, row: D.Row) -> None:
    _reply_field(s, row)
    if s.mode == 2:  # answered where the client connected, through the gateway
        assert s.got["unguarded_room"]["type"] == "room_created"
        assert s.got["direct_hello_join"]["type"] == "welcome"


@check("replies:error", "replies:error.suppressed")
def _error(s: Session, row: D.Row) -> None:
    assert s.got["suppressed"]["suppressed"] >= 1
    e = s.got["bad_id"]
    err(e, "bad_message")
    assert "re" not in e  # an invalid id is not echoed


@check("replies:room")
def _room(s: Session, row: D.Row) -> None:
    assert s.t.of("room") and s.got["state"]["type"] == "room"


@check("replies:joined.kind")
def _joined_kind(s: Session, row: D.Row) -> None:
    assert s.got["joined_host"]["kind"] == "human"


@check("replies:joined.reach")
def _joined_reach(s: Session, row: D.Row) -> None:
    j = s.got["joined_host"]
    g = j["geometry"]
    assert j["reach"]["centre"] == g["anchors"][0]
    assert j["reach"]["half_extent"] == g["reach_half_extent"]
    # a HIP outside it is refused
    err(s.got["hip_out_of_range"], "out_of_range")


# room info, seat info, geometry: every one the server sent has every documented field


def _room_infos(s: Session) -> Iterator[tuple[dict[str, Any], bool]]:
    """Every room info received, and whether it came in a list."""
    for m in s.t.json:
        if m["type"] == "room":
            yield {k: v for k, v in m.items() if k not in ("type", "re")}, False
        elif m["type"] in ("rooms", "welcome"):
            for r in m["rooms"]:
                yield r, True
        elif m["type"] in ("room_created", "joined"):
            yield m["state"], False


@check("room_info:*")
def _room_info(s: Session, row: D.Row) -> None:
    infos = list(_room_infos(s))
    assert infos
    for info, _listed in infos:
        if row.key == "host":
            assert "host" not in info, info  # only in a cluster's lists (test_cluster)
        else:
            assert row.key in info, (row.key, info)
    values = [i[row.key] for i, _ in infos if row.key in i]
    if row.key == "state":
        assert set(values) <= {"waiting", "countdown", "playing", "over"}
        assert {"waiting", "playing"} <= set(values)
    if row.key in ("scores", "seats"):
        assert all(len(v) == 4 for v in values)


@check("seat_info:*")
def _seat_info(s: Session, row: D.Row) -> None:
    seats = [x for info, _ in _room_infos(s) for x in info["seats"]]
    header = _replay_header(s.got["replay_file"][1])
    for x in seats + header["players"]:
        assert row.key in x, (row.key, x)
    if row.key == "kind":
        assert {x["kind"] for x in seats} == {"empty", "human", "bot"}
    if row.key == "edge":
        assert all(x["edge"] == TABLES["seats"].rows[x["seat"]]["edge"].strip() for x in seats)


@check("geometry:*")
def _geometry(s: Session, row: D.Row) -> None:
    g = s.got["joined_host"]["geometry"]
    assert row.key in g
    want = {"scene": "tiny", "n": TINY.n, "frame_dt": 0.001, "mesh_hz": 30,
            "edges": [r["edge"].strip() for r in TABLES["seats"].rows]}
    if row.key in want:
        assert g[row.key] == want[row.key]
    if row.key == "stiffness":
        assert g["stiffness"] == pytest.approx(read(s.got["corner"], "corner", 64), rel=1e-6)
    if row.key == "ball_radius":
        assert g["ball_radius"] == pytest.approx(read(s.got["mesh"], "mesh", 64), rel=1e-6)
    if row.key == "anchors":
        assert np.array(g["anchors"]).shape == (4, 3)
    if row.key in ("size", "height", "reach_half_extent"):
        assert np.all(np.array(g[row.key]) > 0)


# events: each documented one, and each of its fields, was sent


@check("events:*")
def _event(s: Session, row: D.Row) -> None:
    evs = s.t.events(row.key)
    assert evs, f"no {row.key} event was received"
    for e in evs:
        assert {"event", "room", "frame", "time"} <= set(e)
    if row.field is not None:
        assert any(row.field in e for e in evs), f"no {row.key} event carried {row.field}"


@check("events:seat.reason")
def _seat_reasons(s: Session, row: D.Row) -> None:
    listed = set(re.findall(r"`([a-z_]+)`", row.text.split("(", 1)[1]))
    seen = {e["reason"] for e in s.t.events("seat") if "reason" in e}
    assert seen <= listed, seen - listed
    assert seen == listed, listed - seen  # each documented reason was seen here


@check("events:score", "events:score.conceded_by", "events:score.scorers")
def _score(s: Session, row: D.Row) -> None:
    sc = s.got["score"]
    assert sc["conceded_by"] == sc["edge"]  # every seat held
    assert sorted(sc["scorers"]) == [x for x in range(4) if x != sc["edge"]]


@check("events:replay_saved", "events:replay_saved.bytes")
def _replay_saved(s: Session, row: D.Row) -> None:
    status, body, _ = s.got["replay_file"]
    assert status == 200 and len(body) == s.got["replay_saved"]["bytes"]


@check("events:cannot_start", "events:cannot_start.reason")
def _cannot_start(s: Session, row: D.Row) -> None:
    assert "bots" in s.got["cannot_start_event"]["reason"]


@check("events:replay_failed", "events:replay_failed.id", "events:replay_failed.round",
       "events:replay_failed.reason")
def _replay_failed(s: Session, row: D.Row, edge: Edge) -> None:
    f = edge.got["replay_failed"]
    assert f["reason"].startswith("recording is off") and f["round"] >= 1 and f["id"]


@check("events:room_stopped", "events:room_stopped.reason", "errors:room_stopped")
def _room_stopped(s: Session, row: D.Row, edge: Edge) -> None:
    assert "non-finite" in edge.got["room_stopped_event"]["reason"]
    err(edge.got["room_stopped_error"], "room_stopped")


# the replay file's header -----------------------------------------------------------------


@check("replay_header:*")
def _replay_header_field(s: Session, row: D.Row) -> None:
    status, body, _ = s.got["replay_file"]
    h = _replay_header(body)  # a private room's round, cut by its 1 s cap: every field
    assert row.key in h, row.key
    score = s.got["score"]
    want = {"format": "clothball-replay", "replay_version": 1, "protocol_version": 1,
            "id": s.got["replay_saved"]["id"], "room_id": s.got["created"]["room"],
            "room_name": CONF_ROOM["name"], "scene": "tiny", "round": score["round"],
            "conceded_edge": score["edge"], "conceded_by": score["conceded_by"],
            "scorers": score["scorers"], "scores": score["scores"],
            "first_to": CONF_ROOM["first_to"], "tail_s": 1.0, "track_hz": 100.0,
            "geometry": s.got["joined_host"]["geometry"]}
    if row.key in want:
        assert h[row.key] == want[row.key], (row.key, h[row.key])
    if row.key == "players":
        assert [p["seat"] for p in h["players"]] == [0, 1, 2, 3]
        assert h["players"][0]["held_by"] == [{"kind": "human", "name": "host"}]
    if row.key in ("started_at", "ended_at"):
        assert abs(h[row.key] - time.time()) < 3600
    if row.key == "duration_s":
        assert 0 < h["duration_s"] <= h["ended_at"] - h["started_at"] + h["tail_s"]
    if row.key == "access":
        assert re.fullmatch(r"[0-9a-f]{64}", h["access"])
        assert s.got["created"]["code"] not in json.dumps(h)
    if row.key == "scene_data":
        assert h["scene_data"]["cloth"]["n"] == TINY.n


# binary ---------------------------------------------------------------------------------------


@check("header:0")
def _h_type(s: Session, row: D.Row) -> None:
    types = header_types()
    assert types == P.BINARY_TYPES
    assert s.got["corner"][0] == 2 and s.got["mesh"][0] == 3  # CORNER, MESH
    assert read(s.got["corner"], "corner", 92) == 7  # a HIP (1) was applied
    raw = gzip.decompress(s.got["replay_file"][1])
    hlen = struct.unpack_from("<I", raw, 20)[0]
    off, kinds = 24 + hlen, set()
    while off < len(raw):
        kind, n = struct.unpack_from("<BI", raw, off)
        if kind == 1:
            kinds.add(types[raw[off + 5]])
        off += 5 + n
    assert kinds == {"MESH", "TRACK"}  # replay files only carry TRACK


@check("header:1")
def _h_version(s: Session, row: D.Row) -> None:
    assert s.got["corner"][1] == 1 and s.got["mesh"][1] == 2  # MESH: its version 2
    err(s.got["hip_version"], "bad_version")


@check("header:2")
def _h_flags(s: Session, row: D.Row) -> None:
    assert read(s.got["corner"], "header", 2) == 0
    assert read(s.got["mesh"], "header", 2) & ~3 == 0
    err(s.got["hip_flags"], "bad_binary")


@check("header:4")
def _h_seq(s: Session, row: D.Row) -> None:
    for b, table in ((s.got["corner"], "corner"), (s.got["mesh"], "mesh")):
        assert read(b, "header", 4) == read(b, table, 16) % 2**32


@check("header:8")
def _h_time(s: Session, row: D.Row) -> None:
    ct, mt = read(s.got["corner"], "header", 8), read(s.got["mesh"], "header", 8)
    # server time: the MESH came after the CORNER, the pong after both
    assert 0 < ct <= s.got["pong_in_room"]["server_time"]
    assert 0 < mt <= s.got["pong_in_room"]["server_time"]


@check("corner:*")
def _corner(s: Session, row: D.Row) -> None:
    b = s.got["corner"]
    assert len(b) == 104
    hip, seq, hip_time = s.got["hip"]
    g = s.got["joined_host"]["geometry"]
    off = int(row.key)
    v = read(b, "corner", off)
    pos, k = read(b, "corner", 28), read(b, "corner", 64)
    if off == 16:
        assert v > 0 and v % 2**32 == read(b, "header", 4)
    elif off == 24:
        assert v == 0 and b[25:28] == b"\0\0\0"  # the host's seat, then padding
    elif off == 28:
        assert np.linalg.norm(v - np.array(g["anchors"][0])) < g["size"]
    elif off == 52:
        assert v == pytest.approx(-k * (hip - pos), rel=1e-4, abs=1e-4)
    elif off == 64:
        assert v == pytest.approx(g["stiffness"], rel=1e-6)
    elif off in (40, 68, 80):
        assert np.all(np.isfinite(v))
    elif off == 92:
        assert v == seq
    elif off == 96:
        assert v == hip_time


@check("mesh:*")
def _mesh(s: Session, row: D.Row) -> None:
    b = s.got["mesh"]
    g = s.got["joined_host"]["geometry"]
    n = g["n"]
    off = int(row.key)
    if off == 116:
        p = decode_mesh_payload(b)
        assert p.shape == (n, n, 3)
        lo, hi = read(b, "mesh", 28), read(b, "mesh", 40)
        assert np.all(p >= lo - 1e-6) and np.all(p <= hi + 1e-6)
        # node (0,0), (0,n-1), (n-1,n-1), (n-1,0) are corners 0..3: nearest their anchors
        a = np.array(g["anchors"])
        for c, (i, j) in enumerate([(0, 0), (0, n - 1), (n - 1, n - 1), (n - 1, 0)]):
            assert np.argmin(np.linalg.norm(a - p[i, j], axis=1)) == c
        return
    v = read(b, "mesh", off)
    if off == 16:
        assert v % 2**32 == read(b, "header", 4)
    elif off == 24:
        assert v == n and b[26:28] == b"\0\0"
    elif off == 28:
        assert np.all(v <= read(b, "mesh", 40))
    elif off == 40:
        assert np.all(v >= read(b, "mesh", 28))
    elif off == 52:
        assert np.all(np.isfinite(v))
    elif off == 64:
        assert v == pytest.approx(g["ball_radius"], rel=1e-6)
    elif off == 68:
        hands = v.reshape(4, 3)
        assert hands[0] == pytest.approx(s.got["hip"][0], abs=1e-6)  # the host's HIP


# errors ---------------------------------------------------------------------------------------

ERROR_CASES = {
    "bad_json": ["bad_json", "bad_json_nan"], "bad_message": ["bad_id"],
    "bad_binary": ["hip_flags", "hip_short"], "bad_version": ["hip_version"],
    "out_of_range": ["hip_out_of_range"], "unknown_type": ["unknown_type"],
    "too_big": ["too_big"], "rate_limited": ["rate_limited"],
    "not_allowed": ["state_lobby", "hip_spectator", "second_hello"],
    "unknown_room": ["unknown_room"], "bad_seat": ["remove_no_bot"], "bad_code": ["bad_code"],
    "room_full": ["room_full"], "illegal_move": ["start_running"],
    "cannot_start": ["cannot_start_error"], "too_many_rooms": ["too_many_rooms"],
}


@check(*(f"errors:{c}" for c in ERROR_CASES))
def _error_code(s: Session, row: D.Row) -> None:
    for name in ERROR_CASES[row.key]:
        err(s.got[name], row.key)


@check("errors:bad_token")
def _bad_token(s: Session, row: D.Row) -> None:
    err(s.got["requests:join.token"], "bad_token")


@check("errors:server_busy")
def _server_busy(s: Session, row: D.Row, edge: Edge) -> None:
    err(edge.got["server_busy"], "server_busy")


# closes ---------------------------------------------------------------------------------------


@check("closes:1008")
def _close_1008(s: Session, row: D.Row) -> None:
    assert s.got["close_bad_hello"] == 1008 and s.got["hello_role_king"][1] == 1008


@check("closes:1009")
def _close_1009(s: Session, row: D.Row) -> None:
    assert s.got["close_1009"] == 1009


@check("closes:1011")
def _close_1011(s: Session, row: D.Row, edge: Edge) -> None:
    assert edge.got["close_1011"] == 1011


@check("closes:4000")
def _close_4000(s: Session, row: D.Row) -> None:
    assert s.got["replaced_close"] == 4000


# HTTP -----------------------------------------------------------------------------------------


@check("http:/")
def _http_root(s: Session, row: D.Row) -> None:
    status, body, headers = http_get_url(s.http_url)
    assert status == 200 and "text/html" in headers["Content-Type"] and b"<html" in body.lower()


@check("http:/static/<path>")
def _http_static(s: Session, row: D.Row) -> None:
    status, body, _ = http_get_url(s.http_url + "static/protocol.js")
    web = Path(__file__).resolve().parents[2] / "assets" / "web" / "protocol.js"
    assert status == 200 and body == web.read_bytes()
    assert http_get_url(s.http_url + "static/%2e%2e/%2e%2e/pyproject.toml")[0] == 404


@check("http:/healthz")
def _http_healthz(s: Session, row: D.Row) -> None:
    status, body, _ = http_get_url(s.http_url + "healthz")
    assert status == 200 and body.strip() == b"ok"


@check("http:/api/rooms")
def _http_rooms(s: Session, row: D.Row) -> None:
    status, body, _ = http_get_url(s.http_url + "api/rooms")
    rooms = json.loads(body)["rooms"]
    ids = {r["id"] for r in rooms}
    assert status == 200 and "main" in ids and s.got["created"]["room"] not in ids
    assert all(set(r) <= {x.key for x in ROWS.values() if x.table == "room_info"}
               for r in rooms)


@check("http:/api/replays")
def _http_replays(s: Session, row: D.Row) -> None:
    rid = s.got["replay_saved"]["id"]
    for name in ("replays_room", "replays_player"):
        status, body, _ = s.got[name]
        listing = json.loads(body)
        assert status == 200 and rid in [r["id"] for r in listing["replays"]]
        assert listing["total"] == len(listing["replays"])
        r = next(r for r in listing["replays"] if r["id"] == rid)
        assert r["private"] is True and r["bytes"] == s.got["replay_saved"]["bytes"]
        assert r["players"][0]["name"] == "host"
    assert json.loads(s.got["replays_room_no_code"][1])["total"] == 0  # private: the code
    assert s.got["replays_bad_limit"][0] == 400


@check("http:/api/replays/<id>")
def _http_replay(s: Session, row: D.Row) -> None:
    status, body, headers = s.got["replay_file"]
    assert status == 200 and headers["Content-Type"] == "application/octet-stream"
    assert headers["Access-Control-Allow-Origin"] == "*"
    assert _replay_header(body)["id"] == s.got["replay_saved"]["id"]
    assert s.got["replay_no_code"][0] == 404


@check("http:/api/stats")
def _http_stats(s: Session, row: D.Row) -> None:
    for st in s.got["stats"]:  # each process's
        for k in re.findall(r"`([a-z_]+)`", row.cells["answer"]):
            if k not in ("on", "off", "ok"):
                assert k in st, k
        assert st["recording"] == "on"
    assert sum(st["rounds_saved"] for st in s.got["stats"]) >= 1


@check("http:/metrics")
def _http_metrics(s: Session, row: D.Row) -> None:
    for (status, body, headers), st in zip(s.got["metrics"], s.got["stats"], strict=True):
        assert status == 200 and headers["Content-Type"].startswith("text/plain")
        families = list(text_string_to_metric_families(body.decode()))
        samples = {(m.name, tuple(sorted(m.labels.items()))): m.value
                   for f in families for m in f.samples}
        # Every documented metric is there (a per-room one without samples while this
        # process has no public room: its HELP and TYPE).
        names = {f.name + ("_total" if f.type == "counter" else "") for f in families}
        for k in re.findall(r"`(clothball_[a-z_]+)`", row.cells["answer"]):
            assert k in names, k
        assert samples[("clothball_rounds_saved_total", ())] == st["rounds_saved"]
        assert samples[("clothball_recording", ())] == 1.0
        assert {dict(lab)["room"] for name, lab in samples
                if name == "clothball_room_frames_total"} == set(st["rooms"])


for _rid in BAD_FIELDS:  # the rows with no check of their own besides the refusal
    CHECKS.setdefault(_rid, _bad_field)


# --- the tests ---------------------------------------------------------------------------------


def test_every_documented_row_has_a_check() -> None:
    missing = [r for r in ROWS if check_for(r) is None]
    assert not missing, f"rows of docs/protocol.md without a check here: {missing}"
    stale = [c for c in CHECKS if not c.endswith(":*") and c not in ROWS]
    assert not stale, f"checks of rows docs/protocol.md no longer has: {stale}"
    tables = {c[:-2] for c in CHECKS if c.endswith(":*")}
    assert tables <= set(TABLES), tables - set(TABLES)


@pytest.mark.parametrize("row_id", list(ROWS))
def test_row(row_id: str, session: Session, request: pytest.FixtureRequest) -> None:
    fn = check_for(row_id)
    assert fn is not None, f"no check for {row_id}"
    args: list[Any] = [session, ROWS[row_id]]
    if "edge" in fn.__code__.co_varnames[:fn.__code__.co_argcount]:
        args.append(request.getfixturevalue("edge"))
    fn(*args)


def test_nothing_undocumented_is_sent(session: Session) -> None:
    """Every JSON message the session received is of a documented type with documented
    fields; every event is documented with its fields; room and seat infos and geometry
    hold documented fields only."""
    replies = {r.key for r in ROWS.values() if r.table == "replies" and r.field is None}
    events = set(_table_keys("events"))
    room_info, seat_info = set(_table_keys("room_info")), set(_table_keys("seat_info"))
    for m in session.t.json:
        assert m["type"] in replies, m
        if m["type"] == "event":
            assert m["event"] in events, m
            allowed = _doc_fields("replies", "event") | _doc_fields("events", m["event"])
        elif m["type"] == "room":
            allowed = room_info | _doc_fields("replies", "room")
        else:
            allowed = _doc_fields("replies", m["type"])
        assert set(m) - {"type"} <= allowed, (m["type"], set(m) - {"type"} - allowed)
        if m["type"] == "joined":
            assert set(m["geometry"]) <= set(_table_keys("geometry"))
    header = _replay_header(session.got["replay_file"][1])
    assert set(header) <= set(_table_keys("replay_header")), \
        set(header) - set(_table_keys("replay_header"))
    for p in header["players"]:
        assert set(p) <= set(_table_keys("seat_info")) | {"held_by"}
    for info, _ in _room_infos(session):
        assert set(info) <= room_info, set(info) - room_info
        for x in info["seats"]:
            assert set(x) <= seat_info, set(x) - seat_info
    assert {c for c, _ in session.t.closes if c not in (1000,)} <= \
        {int(k) for k in _table_keys("closes")}
    assert not session.got["errors_logged"], session.got["errors_logged"]


def test_what_the_server_can_send_is_documented() -> None:
    """From the code: the codec's error codes and binary types, the websocket handler
    table, and every message type, event and error code the server's modules name, are
    the doc's."""
    assert set(P.ERROR_CODES) == set(_table_keys("errors"))
    assert header_types() == P.BINARY_TYPES
    src = "\n".join(p.read_text() for p in
                    (Path(__file__).resolve().parents[2] / "server").glob("*.py")
                    if "bench" not in p.name)
    src += (Path(__file__).resolve().parents[2] / "game" / "wire" / "protocol.py").read_text()
    codes = set(re.findall(r'(?:ProtocolError\(\s*|\.error\()"([a-z_]+)"', src))
    assert codes <= set(P.ERROR_CODES), codes - set(P.ERROR_CODES)
    events = set(re.findall(r'\.event\(\s*"([a-z_]+)"', src))
    assert events <= set(_table_keys("events")), events - set(_table_keys("events"))
    closes = {int(c) for c in re.findall(r"close\((\d{4}),", src)}
    assert closes and closes <= {int(k) for k in _table_keys("closes")}, closes
    types = set(re.findall(r'"type": "([a-z_]+)"', src)) - {"join"}  # hello carries a join
    replies = {r.key for r in ROWS.values() if r.table == "replies" and r.field is None}
    assert types <= replies, types - replies


def test_the_handler_table_is_the_documented_requests() -> None:
    class Srv:  # WsEndpoint needs nothing of its server to build its table
        pass

    handlers = set(WsEndpoint(Srv()).handlers)  # type: ignore[arg-type]
    assert handlers == set(_table_keys("requests"))
