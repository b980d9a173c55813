"""The game server: one port, the websocket endpoint ``/ws`` and a small HTTP surface.

HTTP (GET only):

* ``/`` the spectator page (``assets/web/index.html``, or a placeholder until it exists)
* ``/static/<path>`` files under ``assets/web/`` (no path traversal)
* ``/healthz`` ``ok``
* ``/api/rooms`` public rooms as JSON
* ``/api/replays`` recorded rounds as JSON (``?limit=&offset=&room=&player=&code=``)
* ``/api/replays/<id>`` one replay file (see ``server.store``; a private room's: ``?code=``)
* ``/api/stats`` the server's own counters (frame lateness, messages, CPU time)

The websocket protocol is in ``docs/protocol.md``; handlers below are thin: they parse,
check and hand over to the lobby and the rooms, and every bad message gets a JSON error
while the room runs on. What a client may do is bounded by ``server.limits.Limits``
(``docs/security.md``).
"""

from __future__ import annotations

import asyncio
import collections
import email.utils
import http
import json
import logging
import math
import mimetypes
import os
import socket
import sqlite3
import time
import urllib.parse
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from ..game.scene import ASSETS, Scene
from . import protocol as P
from .binary_hook import BinaryHook
from .conn import Conn
from .limits import DEFAULT, Limits
from .lobby import Lobby, parse_settings
from .protocol import ProtocolError
from .room import Room, RoomSettings
from .store import ReplayStore, access_key

log = logging.getLogger("clothball.server")

WEB_DIR = ASSETS / "web"
LOBBY_PUSH_S = 0.5  # how often lobby clients' room list is checked for changes

PLACEHOLDER_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>clothball</title></head>
<body><h1>clothball</h1>
<p>The spectator page is not installed yet. Live rooms: <a href="/api/rooms">/api/rooms</a>,
recorded rounds: <a href="/api/replays">/api/replays</a>.</p></body></html>
"""


class _Connection(BinaryHook, ServerConnection):
    """The server's connection: HIPs go straight to ``on_binary`` once the handler has set
    it, when it starts its read loop (see ``binary_hook``)."""


class GameServer:
    """The clothball server. ``await start()``, then ``await stop()`` (or ``run_forever``)."""

    def __init__(self, data_dir: Path | str, *, scenes: dict[str, Scene] | None = None,
                 backend: str = "auto", host: str = "127.0.0.1", port: int = 8765,
                 bots: int = 0, room_settings: RoomSettings | None = None,
                 default_room: bool = True, web_dir: Path | None = None,
                 bot_factory: Callable[..., Any] | None = None,
                 hello_timeout: float | None = None, limits: Limits | None = None,
                 origins: tuple[str, ...] | None = None) -> None:
        if scenes is None:
            scenes = {"classic": Scene.load("classic")}
        self.scenes = scenes
        self.backend = backend
        self.host = host
        self.port = port
        self.bots = max(0, min(4, bots))
        self.room_settings = room_settings
        self.default_room = default_room
        self.web_dir = web_dir or WEB_DIR
        self.data_dir = Path(data_dir)
        self.epoch = time.perf_counter()
        self.limits = limits or DEFAULT
        if hello_timeout is not None:
            self.limits = self.limits.replace(hello_timeout=hello_timeout)
        self.origins = origins  # websocket Origin allow-list (None: any)
        # A data directory that cannot be written does not stop the game: matches go on
        # without recording, and every place that would show replays says why.
        self.store: ReplayStore | None = None
        self.recording_error: str | None = None
        try:
            self.store = ReplayStore(self.data_dir)
        except (OSError, sqlite3.Error) as e:
            self.recording_error = f"data directory {str(self.data_dir)!r} is unusable: {e}"
            log.error("recording is off: %s", self.recording_error)
        self.lobby = Lobby(scenes, self, backend=backend, epoch=self.epoch,
                           max_rooms=self.limits.max_rooms)
        self.clients: set[Conn] = set()
        self.per_address: collections.Counter[str] = collections.Counter()
        self._server: Server | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._saves: set[asyncio.Task[Any]] = set()
        self._bot_factory = bot_factory
        self.main_room: Room | None = None
        self.stats = {"messages_in": 0, "messages_out": 0, "bad_messages": 0, "rounds_saved": 0,
                      "rounds_not_saved": 0, "refused_connections": 0, "rooms_stopped": 0}
        self._cpu0 = time.process_time()
        self._wall0 = time.perf_counter()

    # --- life -----------------------------------------------------------------------------
    async def start(self) -> tuple[str, int]:
        self._server = await serve(
            self._handler, self.host, self.port, process_request=self._process_request,
            max_size=self.limits.max_message_bytes, max_queue=64, compression=None,
            create_connection=_Connection,
            ping_interval=self.limits.ping_interval, ping_timeout=self.limits.ping_timeout,
            close_timeout=2,
        )
        sock = next(iter(self._server.sockets))
        self.port = sock.getsockname()[1]
        if self.default_room:
            settings = self.room_settings or RoomSettings(autoplay=True)
            self.main_room = self.lobby.create("main", public=True, settings=settings,
                                               permanent=True, room_id="main")
            for _ in range(self.bots):
                self.main_room.add_bot(None, settings.bot_difficulty)
        self._spawn(self._housekeeping())
        self._spawn(self._push_room_lists())
        return self.host, self.port

    @property
    def ws_url(self) -> str:
        host = self.host if self.host not in ("0.0.0.0", "::", "") else "127.0.0.1"
        if ":" in host:
            host = f"[{host}]"
        return f"ws://{host}:{self.port}/ws"

    @property
    def http_url(self) -> str:
        return self.ws_url.replace("ws://", "http://", 1)[: -len("/ws")] + "/"

    async def stop(self) -> None:
        """Stop accepting, close every connection and room, finish the writes under way."""
        if self._server is not None:
            self._server.close(close_connections=True)
        for t in list(self._tasks):
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._server is not None:
            await self._server.wait_closed()
        await self.lobby.close()
        if self._saves:
            await asyncio.gather(*self._saves, return_exceptions=True)
        if self.store is not None:
            self.store.close()

    def _spawn(self, coro: Any) -> asyncio.Task[Any]:
        t = asyncio.create_task(coro)
        self._tasks.add(t)
        t.add_done_callback(self._tasks.discard)
        return t

    async def _housekeeping(self) -> None:
        while True:
            await asyncio.sleep(10.0)
            await self.lobby.close_idle(asyncio.get_running_loop().time())

    async def _push_room_lists(self) -> None:
        """Lobby clients get the public room list again whenever it changes (rooms opened or
        closed, seats, phases, scores); the frame counter alone is not a change."""
        def key(rooms: list[dict[str, Any]]) -> str:
            return json.dumps([{**r, "frame": 0} for r in rooms], sort_keys=True)

        last = key(self.lobby.listing())
        while True:
            await asyncio.sleep(LOBBY_PUSH_S)
            rooms = self.lobby.listing()
            now = key(rooms)
            if now == last:
                continue
            last = now
            msg = {"type": "rooms", "rooms": rooms}
            for c in self.clients:
                if c.role == "lobby" and c.hello_done:
                    c.send_json(msg)

    # --- RoomHost -------------------------------------------------------------------------
    def spawn_bot(self, room: Room, seat: int, token: str, difficulty: float) -> None:
        factory = self._bot_factory
        if factory is None:
            from ..game.bots import run_bot

            factory = run_bot
        self._spawn(factory(self.ws_url, room.id, token, difficulty))

    def room_stopped(self, room: Room, reason: str) -> None:
        """A room's simulation failed: it leaves the lobby; the other rooms run on."""
        self.stats["rooms_stopped"] += 1
        log.error("room %s stopped: %s", room.id, reason)
        if self.lobby.rooms.get(room.id) is room:
            self._spawn(self.lobby.remove(room.id))

    def save_round(self, header: dict[str, Any], records: list[tuple[int, bytes]]) -> None:
        room = self.lobby.rooms.get(header["room_id"])
        if room is not None and room.code is not None:
            # A private room's rounds are listed and served only to holders of its code.
            header = {**header, "access": access_key(room.id, room.code)}

        def failed(reason: str) -> None:
            self.stats["rounds_not_saved"] += 1
            r = self.lobby.rooms.get(header["room_id"])
            if r is not None:
                r.event("replay_failed", id=header.get("id"), round=header.get("round"),
                        reason=reason)

        async def save() -> None:
            store = self.store
            if store is None:
                failed(f"recording is off: {self.recording_error}")
                return
            try:
                row = await asyncio.to_thread(store.save, header, records)
            except (OSError, sqlite3.Error) as e:
                # Disk full, read-only, gone: this round is lost, the match goes on.
                log.error("could not save round %s: %s", header.get("id"), e)
                failed(f"could not write the replay: {e}")
                return
            except Exception as e:  # pragma: no cover - a bug must not stop the match
                log.exception("could not save round %s", header.get("id"))
                failed(f"could not write the replay: {e}")
                return
            self.stats["rounds_saved"] += 1
            r = self.lobby.rooms.get(header["room_id"])
            if r is not None:
                r.event("replay_saved", id=row["id"], round=row["round"], bytes=row["bytes"])

        t = asyncio.create_task(save())
        self._saves.add(t)
        t.add_done_callback(self._saves.discard)

    # --- HTTP -----------------------------------------------------------------------------
    def _response(self, status: int, body: bytes, content_type: str,
                  extra: dict[str, str] | None = None) -> Response:
        headers = Headers([
            ("Date", email.utils.formatdate(usegmt=True)),
            ("Connection", "close"),
            ("Content-Length", str(len(body))),
            ("Content-Type", content_type),
            ("Cache-Control", "no-store"),
            ("X-Content-Type-Options", "nosniff"),
        ])
        for k, v in (extra or {}).items():
            headers[k] = v
        st = http.HTTPStatus(status)
        return Response(st.value, st.phrase, headers, body)

    def _json(self, obj: Any, status: int = 200) -> Response:
        return self._response(status, json.dumps(obj, allow_nan=False).encode(),
                              "application/json")

    def _error(self, status: int, message: str) -> Response:
        return self._json({"error": message, "status": status}, status)

    async def _process_request(self, connection: ServerConnection, request: Request
                               ) -> Response | None:
        # Split by hand: urlsplit reads "//host" as an authority and raises on "//[".
        path, _, query = request.path.partition("#")[0].partition("?")
        if path == "/ws":
            origin = request.headers.get("Origin")
            # Browsers always send Origin; other clients need not. The allow-list stops a
            # page on another site from using a visitor's browser to play or watch here.
            if self.origins is not None and origin is not None and origin not in self.origins:
                self.stats["refused_connections"] += 1
                return self._error(403, f"origin {origin[:100]!r} is not allowed here")
            if len(self.clients) >= self.limits.max_clients:
                self.stats["refused_connections"] += 1
                return self._error(503, f"server full ({self.limits.max_clients} connections)")
            return None
        try:
            if path == "/api/rooms":  # live state: read on the loop that changes it
                return self._json({"rooms": self.lobby.listing()})
            if path == "/api/stats":
                if urllib.parse.parse_qs(query).get("reset") == ["1"]:
                    for room in self.lobby.rooms.values():
                        room.sim.stats.lateness.clear()
                return self._json(self.stats_snapshot())
            # Files and the index are read on a worker thread: the room loops go on.
            return await asyncio.to_thread(self._route, path, urllib.parse.parse_qs(query))
        except Exception:  # pragma: no cover - never take the server down on a request
            log.exception("HTTP %s failed", path)
            return self._error(500, "internal error")

    def _route(self, path: str, query: dict[str, list[str]]) -> Response:
        if path in ("/", "/index.html"):
            index = self.web_dir / "index.html"
            if index.is_file():
                return self._response(200, index.read_bytes(), "text/html; charset=utf-8")
            return self._response(200, PLACEHOLDER_PAGE.encode(), "text/html; charset=utf-8")
        if path == "/healthz":
            return self._response(200, b"ok\n", "text/plain; charset=utf-8")
        if path == "/api/replays" or path.startswith("/api/replays/"):
            return self._replays(path, query)
        if path.startswith("/static/"):
            return self._static(path[len("/static/"):])
        return self._error(404, f"no such path {path[:200]!r}")

    def _replays(self, path: str, query: dict[str, list[str]]) -> Response:
        if self.store is None:
            return self._error(503, f"recording is off: {self.recording_error}")

        def one(key: str, max_len: int = 64) -> str | None:
            v = query.get(key, [None])[0]
            if v is not None and (len(v) > max_len or not v.isprintable()):
                raise ValueError(f"{key}: at most {max_len} printable characters")
            return v

        try:
            room, player, code = one("room"), one("player", 32), one("code")
            limit = min(1000, max(1, int(query.get("limit", ["100"])[0])))
            offset = min(2**62, max(0, int(query.get("offset", ["0"])[0])))
        except ValueError as e:
            msg = str(e) if ":" in str(e) else "limit and offset must be whole numbers"
            return self._error(400, msg)
        if path == "/api/replays":
            return self._json({
                "replays": self.store.list(limit, offset, room, player=player, code=code),
                "total": self.store.count(room, player=player, code=code),
            })
        rid = path[len("/api/replays/"):]
        if rid.endswith(".cbr"):
            rid = rid[:-4]
        p = self.store.path_of(rid, code=code)
        if p is None:
            return self._error(404, f"no replay {rid[:100]!r}")
        return self._response(200, p.read_bytes(), "application/octet-stream", {
            "Content-Disposition": f'attachment; filename="{rid}.cbr"',
        })

    def _static(self, rel: str) -> Response:
        rel = urllib.parse.unquote(rel)
        root = self.web_dir.resolve()
        if "\x00" in rel or rel.startswith(("/", "\\")):
            return self._error(404, "not found")
        try:
            target = (root / rel).resolve()
        except (OSError, RuntimeError, ValueError):
            return self._error(404, "not found")
        if not target.is_relative_to(root) or not target.is_file():
            return self._error(404, "not found")
        ctype = mimetypes.guess_type(target.name)[0] or "application/octet-stream"
        if ctype.startswith("text/") or ctype in ("application/javascript",):
            ctype += "; charset=utf-8"
        return self._response(200, target.read_bytes(), ctype)

    def stats_snapshot(self) -> dict[str, Any]:
        rooms = {}
        for rid, room in self.lobby.rooms.items():
            lat = np.array(room.sim.stats.lateness[-100_000:]) * 1e3
            st = room.sim.stats
            rooms[rid] = {
                "frames": st.frames, "steps": st.steps, "skipped_frames": st.skipped_frames,
                "meshes": st.meshes, "substeps": room.sim.cloth.substeps,
                "backend": room.sim.cloth.backend, "n": room.scene.n,
                "lateness_ms": _percentiles(lat),
            }
        return {
            "uptime_s": time.perf_counter() - self._wall0,
            "recording": "on" if self.store is not None else f"off: {self.recording_error}",
            "cpu_s": time.process_time() - self._cpu0,
            "clients": len(self.clients),
            **self.stats,
            "messages_out": self.stats["messages_out"] + sum(c.sent for c in self.clients),
            "rooms": rooms,
        }

    # --- websocket ------------------------------------------------------------------------
    async def _handler(self, ws: ServerConnection) -> None:
        conn = Conn(ws, self.limits)
        self.clients.add(conn)
        sock = ws.transport.get_extra_info("socket") if ws.transport is not None else None
        if sock is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF,
                                self.limits.socket_send_buffer)
            except OSError:  # pragma: no cover - not settable on this platform
                pass
        self.per_address[conn.address] += 1
        try:
            if self.per_address[conn.address] > self.limits.conns_per_address:
                self.stats["refused_connections"] += 1
                await ws.close(1008, f"too many connections from {conn.address} (limit "
                                     f"{self.limits.conns_per_address})")
                return
            timeout = self.limits.hello_timeout
            try:
                first = await asyncio.wait_for(ws.recv(), timeout)
            except TimeoutError:
                conn.error("bad_message", f"no hello within {timeout:g} s")
                await asyncio.sleep(0.05)
                await ws.close(1008, "no hello")
                return
            if not await self._hello(conn, first):
                await asyncio.sleep(0.05)  # let the error go out first
                await ws.close(1008, "hello refused")
                return
            if isinstance(ws, _Connection):
                ws.on_binary = lambda data: self._on_binary_now(conn, data)
            async for message in ws:
                self.stats["messages_in"] += 1
                conn.received += 1
                if isinstance(message, bytes):
                    self._on_binary(conn, message)
                else:
                    self._on_text(conn, message)
                if conn.closed:
                    break
        except ConnectionClosed:
            pass
        finally:
            if isinstance(ws, _Connection):
                ws.on_binary = None
            self.clients.discard(conn)
            self.per_address[conn.address] -= 1
            if self.per_address[conn.address] <= 0:
                del self.per_address[conn.address]
            if conn.room is not None:
                conn.room.disconnected(conn)
            self.stats["messages_out"] += conn.sent
            await conn.finish()

    async def _hello(self, conn: Conn, first: str | bytes) -> bool:
        """The first message must be a hello. True when the connection may go on."""
        try:
            if isinstance(first, bytes):
                raise ProtocolError("bad_message", "the first message must be a JSON hello")
            msg = P.decode_json(first, self.limits.max_control_bytes)
            if msg["type"] != "hello":
                raise ProtocolError("bad_message",
                                    f"the first message must be a hello, got {msg['type']!r}")
            version = msg.get("version")
            if version != P.PROTOCOL_VERSION:
                raise ProtocolError(
                    "bad_version",
                    f"protocol version {version!r} not supported; this server speaks "
                    f"{P.PROTOCOL_VERSION}",
                )
            conn.name = P.field_str(msg, "name", "guest", max_len=32) or "guest"
        except ProtocolError as e:
            self.stats["bad_messages"] += 1
            conn.error(e)
            return False
        conn.hello_done = True
        conn.send_json({
            "type": "welcome",
            "version": P.PROTOCOL_VERSION,
            "client": conn.id,
            "name": conn.name,
            "server_time": time.perf_counter() - self.epoch,
            "scenes": sorted(self.scenes),
            "rooms": self.lobby.listing(),
            "re": P.request_id(msg),
        })
        role = msg.get("role", "lobby")
        if role != "lobby" or "token" in msg:
            # hello may carry a join: the same fields as a join message.
            self._on_control(conn, {**msg, "type": "join"})
        return True

    def _on_text(self, conn: Conn, text: str) -> None:
        if not conn.control_bucket.take():
            self.stats["bad_messages"] += 1
            conn.error("rate_limited", f"at most {conn.control_bucket.rate:g} control "
                                       "messages a second; this one was dropped")
            if conn.rate_dropped():
                conn.drop("too many messages")
            return
        try:
            msg = P.decode_json(text, self.limits.max_control_bytes)
        except ProtocolError as e:
            self.stats["bad_messages"] += 1
            conn.error(e)
            return
        self._on_control(conn, msg)

    def _on_binary_now(self, conn: Conn, data: bytes) -> None:
        """A binary message handed over by ``_Connection`` as it arrives: what the read loop
        of ``_handler`` does with one, which stops reading once the client is closed."""
        if conn.closed:
            return
        self.stats["messages_in"] += 1
        conn.received += 1
        try:
            self._on_binary(conn, data)
        except Exception:  # pragma: no cover - a bug: like a failing handler, close 1011
            log.exception("handling a binary message from client %s failed", conn.id)
            conn.fail("internal error")

    def _on_binary(self, conn: Conn, data: bytes) -> None:
        if not conn.binary_bucket.take():
            self.stats["bad_messages"] += 1
            conn.error("rate_limited", f"at most {conn.binary_bucket.rate:g} binary "
                                       "messages a second; the extra ones are dropped")
            if conn.rate_dropped():
                conn.drop("too many messages")
            return
        try:
            if conn.role != "player" or conn.room is None:
                raise ProtocolError("not_allowed",
                                    f"binary messages are for seated players; you are {conn.role}")
            hip = P.decode_hip(data)
            conn.room.on_hip(conn, hip)
        except ProtocolError as e:
            self.stats["bad_messages"] += 1
            conn.error(e)

    def _on_control(self, conn: Conn, msg: dict[str, Any]) -> None:
        t = msg["type"]
        re = P.request_id(msg)
        handler = getattr(self, f"_msg_{t}", None) if t.isidentifier() else None
        try:
            if handler is None:
                raise ProtocolError("unknown_type", f"unknown message type {t!r}")
            reply = handler(conn, msg)
        except ProtocolError as e:
            self.stats["bad_messages"] += 1
            conn.error(e, re=re)
            return
        if reply is None and re is not None:
            reply = {"type": "ok"}
        if reply is not None:
            if re is not None:
                reply["re"] = re
            conn.send_json(reply)

    # --- control messages -----------------------------------------------------------------
    def _msg_hello(self, conn: Conn, msg: dict[str, Any]) -> dict[str, Any]:
        raise ProtocolError("not_allowed", "hello was already received")

    def _msg_ping(self, conn: Conn, msg: dict[str, Any]) -> dict[str, Any]:
        t = P.field_float(msg, "t", None, -1e12, 1e12)
        return {"type": "pong", "t": t, "server_time": time.perf_counter() - self.epoch}

    def _msg_list_rooms(self, conn: Conn, msg: dict[str, Any]) -> dict[str, Any]:
        return {"type": "rooms", "rooms": self.lobby.listing()}

    def _msg_create_room(self, conn: Conn, msg: dict[str, Any]) -> dict[str, Any]:
        name = P.field_str(msg, "name", "room", max_len=48) or "room"
        scene = P.field_str(msg, "scene", None, max_len=64)
        public = P.field_bool(msg, "public", True)
        settings = parse_settings(msg)
        mine = self.lobby.rooms_of(conn.address)
        if mine >= self.limits.rooms_per_address:
            raise ProtocolError("too_many_rooms", f"{conn.address} already has {mine} open rooms "
                                f"(limit {self.limits.rooms_per_address}); close one first")
        room = self.lobby.create(name, scene, public=public, settings=settings, owner=conn.id,
                                 address=conn.address)
        return {"type": "room_created", "room": room.id, "code": room.code, "state": room.info()}

    def _room_options(self, conn: Conn, msg: dict[str, Any]) -> None:
        rate = P.field_float(msg, "corner_rate", 1000.0, 1.0, 1000.0)
        assert rate is not None
        conn.corner_interval = 0.0 if rate >= 1000.0 else 1.0 / rate - 1e-4
        conn.want_mesh = P.field_bool(msg, "mesh", True)

    def _msg_join(self, conn: Conn, msg: dict[str, Any]) -> dict[str, Any]:
        if conn.room is not None:
            raise ProtocolError("not_allowed", f"already in room {conn.room.id}: leave first")
        token = P.field_str(msg, "token", None, max_len=64)
        role = P.field_str(msg, "role", "player" if token else "spectator", max_len=16)
        self._room_options(conn, msg)
        if token is not None:
            room = self.lobby.get(msg.get("room")) if msg.get("room") is not None else None
            rooms = [room] if room is not None else list(self.lobby.rooms.values())
            for r in rooms:
                try:
                    return r.resume(conn, token)
                except ProtocolError:
                    continue
            raise ProtocolError("bad_token", "reconnect token unknown or expired")
        room = self.lobby.get(msg.get("room"))
        code = P.field_str(msg, "code", None, max_len=64)
        if role == "player":
            seat = P.field_int(msg, "seat", None, -(2**31), 2**31)  # the room names bad seats
            return room.join_player(conn, seat, conn.name, code)
        if role == "spectator":
            room.check_code(code)  # a private room's size is its own business
            if len(room.spectators) >= self.limits.spectators_per_room:
                raise ProtocolError("room_full", f"room {room.id} already has "
                                    f"{len(room.spectators)} spectators (the limit)")
            return room.join_spectator(conn, code)
        raise ProtocolError("bad_message", f"role must be 'player' or 'spectator', got {role!r}")

    def _in_room(self, conn: Conn) -> Room:
        if conn.room is None:
            raise ProtocolError("not_allowed", "not in a room: join one first")
        return conn.room

    def _msg_leave(self, conn: Conn, msg: dict[str, Any]) -> dict[str, Any]:
        room = self._in_room(conn)
        room.leave(conn)
        return {"type": "left", "room": room.id}

    def _msg_ready(self, conn: Conn, msg: dict[str, Any]) -> None:
        self._in_room(conn).set_ready(conn, P.field_bool(msg, "ready", True))

    def _msg_start(self, conn: Conn, msg: dict[str, Any]) -> None:
        self._in_room(conn).request_start(conn)

    def _msg_add_bot(self, conn: Conn, msg: dict[str, Any]) -> None:
        room = self._in_room(conn)
        if not room.may_control(conn):
            raise ProtocolError("not_allowed", "only the room's host can add bots")
        seat = P.field_int(msg, "seat", None, 0, 3)
        difficulty = P.field_float(msg, "difficulty", room.settings.bot_difficulty, 0.0, 1.0)
        assert difficulty is not None
        room.add_bot(seat, difficulty)

    def _msg_remove_bot(self, conn: Conn, msg: dict[str, Any]) -> None:
        room = self._in_room(conn)
        if not room.may_control(conn):
            raise ProtocolError("not_allowed", "only the room's host can remove bots")
        seat = P.field_int(msg, "seat", None, 0, 3, required=True)
        assert seat is not None
        room.remove_bot(seat)

    def _msg_state(self, conn: Conn, msg: dict[str, Any]) -> dict[str, Any]:
        return {"type": "room", **self._in_room(conn).info()}


def _percentiles(values: np.ndarray) -> dict[str, float]:
    if values.size == 0:
        return {"count": 0}
    p50, p99, p999 = np.percentile(values, [50, 99, 99.9])
    return {"count": int(values.size), "p50": float(p50), "p99": float(p99),
            "p999": float(p999), "max": float(values.max()),
            "mean": float(values.mean()) if math.isfinite(values.mean()) else 0.0}


def default_data_dir() -> Path:
    import platformdirs

    return Path(os.environ.get("CLOTHBALL_DATA") or platformdirs.user_data_dir("clothball"))


__all__ = ["GameServer", "default_data_dir"]
