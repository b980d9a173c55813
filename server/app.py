"""The game server: one port, the websocket endpoint ``/ws`` and a small HTTP surface.

HTTP (GET only):

* ``/`` the spectator page (``assets/web/index.html``, or a placeholder until it exists)
* ``/static/<path>`` files under ``assets/web/`` (no path traversal)
* ``/healthz`` ``ok``
* ``/api/rooms`` public rooms as JSON
* ``/api/replays`` recorded rounds as JSON (``?limit=&offset=&room=``)
* ``/api/replays/<id>`` one replay file (see ``server.store``)
* ``/api/stats`` the server's own counters (frame lateness, messages, CPU time)

The websocket protocol is in ``docs/protocol.md``; handlers below are thin: they parse,
check and hand over to the lobby and the rooms, and every bad message gets a JSON error
while the room runs on.
"""

from __future__ import annotations

import asyncio
import email.utils
import http
import json
import logging
import math
import mimetypes
import os
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
from .conn import Conn
from .lobby import Lobby, parse_settings
from .protocol import ProtocolError
from .room import Room, RoomSettings
from .store import ReplayStore

log = logging.getLogger("clothball.server")

WEB_DIR = ASSETS / "web"
HELLO_TIMEOUT = 10.0
MAX_CLIENTS = 512

PLACEHOLDER_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>clothball</title></head>
<body><h1>clothball</h1>
<p>The spectator page is not installed yet. Live rooms: <a href="/api/rooms">/api/rooms</a>,
recorded rounds: <a href="/api/replays">/api/replays</a>.</p></body></html>
"""


class GameServer:
    """The clothball server. ``await start()``, then ``await stop()`` (or ``run_forever``)."""

    def __init__(self, data_dir: Path | str, *, scenes: dict[str, Scene] | None = None,
                 backend: str = "auto", host: str = "127.0.0.1", port: int = 8765,
                 bots: int = 0, room_settings: RoomSettings | None = None,
                 default_room: bool = True, web_dir: Path | None = None,
                 bot_factory: Callable[..., Any] | None = None,
                 hello_timeout: float = HELLO_TIMEOUT) -> None:
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
        self.store = ReplayStore(self.data_dir)
        self.lobby = Lobby(scenes, self, backend=backend, epoch=self.epoch)
        self.clients: set[Conn] = set()
        self._server: Server | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._saves: set[asyncio.Task[Any]] = set()
        self._bot_factory = bot_factory
        self.hello_timeout = hello_timeout
        self.main_room: Room | None = None
        self.stats = {"messages_in": 0, "messages_out": 0, "bad_messages": 0, "rounds_saved": 0}
        self._cpu0 = time.process_time()
        self._wall0 = time.perf_counter()

    # --- life -----------------------------------------------------------------------------
    async def start(self) -> tuple[str, int]:
        self._server = await serve(
            self._handler, self.host, self.port, process_request=self._process_request,
            max_size=P.MAX_MESSAGE_BYTES, max_queue=64, compression=None,
            ping_interval=20, ping_timeout=20, close_timeout=2,
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

    # --- RoomHost -------------------------------------------------------------------------
    def spawn_bot(self, room: Room, seat: int, token: str, difficulty: float) -> None:
        factory = self._bot_factory
        if factory is None:
            from ..game.bots import run_bot

            factory = run_bot
        self._spawn(factory(self.ws_url, room.id, token, difficulty))

    def save_round(self, header: dict[str, Any], records: list[tuple[int, bytes]]) -> None:
        async def save() -> None:
            try:
                row = await asyncio.to_thread(self.store.save, header, records)
            except Exception:
                log.exception("could not save round %s", header.get("id"))
                return
            self.stats["rounds_saved"] += 1
            room = self.lobby.rooms.get(header["room_id"])
            if room is not None:
                room.event("replay_saved", id=row["id"], round=row["round"], bytes=row["bytes"])

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
        url = urllib.parse.urlsplit(request.path)
        path = url.path
        if path == "/ws":
            if len(self.clients) >= MAX_CLIENTS:
                return self._error(503, "server full")
            return None
        try:
            if path == "/api/rooms":  # live state: read on the loop that changes it
                return self._json({"rooms": self.lobby.listing()})
            if path == "/api/stats":
                if urllib.parse.parse_qs(url.query).get("reset") == ["1"]:
                    for room in self.lobby.rooms.values():
                        room.sim.stats.lateness.clear()
                return self._json(self.stats_snapshot())
            # Files and the index are read on a worker thread: the room loops go on.
            return await asyncio.to_thread(self._route, path, urllib.parse.parse_qs(url.query))
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
        if path == "/api/replays":
            try:
                limit = min(1000, max(1, int(query.get("limit", ["100"])[0])))
                offset = max(0, int(query.get("offset", ["0"])[0]))
            except ValueError:
                return self._error(400, "limit and offset must be whole numbers")
            room = query.get("room", [None])[0]
            return self._json({"replays": self.store.list(limit, offset, room),
                               "total": self.store.count()})
        if path.startswith("/api/replays/"):
            rid = path[len("/api/replays/"):]
            if rid.endswith(".cbr"):
                rid = rid[:-4]
            p = self.store.path_of(rid)
            if p is None:
                return self._error(404, f"no replay {rid!r}")
            return self._response(200, p.read_bytes(), "application/octet-stream", {
                "Content-Disposition": f'attachment; filename="{rid}.cbr"',
            })
        if path.startswith("/static/"):
            return self._static(path[len("/static/"):])
        return self._error(404, f"no such path {path!r}")

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
            "cpu_s": time.process_time() - self._cpu0,
            "clients": len(self.clients),
            **self.stats,
            "messages_out": self.stats["messages_out"] + sum(c.sent for c in self.clients),
            "rooms": rooms,
        }

    # --- websocket ------------------------------------------------------------------------
    async def _handler(self, ws: ServerConnection) -> None:
        conn = Conn(ws)
        self.clients.add(conn)
        try:
            try:
                first = await asyncio.wait_for(ws.recv(), self.hello_timeout)
            except TimeoutError:
                conn.error("bad_message", f"no hello within {self.hello_timeout:g} s")
                await asyncio.sleep(0.05)
                await ws.close(1008, "no hello")
                return
            if not await self._hello(conn, first):
                await asyncio.sleep(0.05)  # let the error go out first
                await ws.close(1008, "hello refused")
                return
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
            self.clients.discard(conn)
            if conn.room is not None:
                conn.room.disconnected(conn)
            self.stats["messages_out"] += conn.sent
            await conn.finish()

    async def _hello(self, conn: Conn, first: str | bytes) -> bool:
        """The first message must be a hello. True when the connection may go on."""
        try:
            if isinstance(first, bytes):
                raise ProtocolError("bad_message", "the first message must be a JSON hello")
            msg = P.decode_json(first)
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
            msg = P.decode_json(text)
        except ProtocolError as e:
            self.stats["bad_messages"] += 1
            conn.error(e)
            return
        self._on_control(conn, msg)

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
        room = self.lobby.create(name, scene, public=public, settings=settings, owner=conn.id)
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
