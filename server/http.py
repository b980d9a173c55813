"""The game server's HTTP surface, on the websocket port (GET only):

* ``/`` the spectator page (``assets/web/index.html``, or a placeholder until it exists)
* ``/static/<path>`` files under ``assets/web/`` (no path traversal)
* ``/healthz`` ``ok``
* ``/api/rooms`` public rooms as JSON
* ``/api/replays`` recorded rounds as JSON (``?limit=&offset=&room=&player=&code=``)
* ``/api/replays/<id>`` one replay file (``game.wire.replay``; a private room's: ``?code=``)
* ``/api/stats`` the server's own counters (frame lateness, messages, CPU time)

and the admission of websocket upgrades on ``/ws`` (origin allow-list, connection limit).
"""

from __future__ import annotations

import asyncio
import email.utils
import http
import json
import logging
import mimetypes
import urllib.parse
from pathlib import Path
from typing import Any, Protocol

from websockets.asyncio.server import ServerConnection
from websockets.datastructures import Headers
from websockets.http11 import Request, Response

from .conn import Conn
from .limits import Limits
from .lobby import Lobby
from .replays import ReplayStore

log = logging.getLogger("clothball.server")

PLACEHOLDER_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>clothball</title></head>
<body><h1>clothball</h1>
<p>The spectator page is not installed yet. Live rooms: <a href="/api/rooms">/api/rooms</a>,
recorded rounds: <a href="/api/replays">/api/replays</a>.</p></body></html>
"""


class HttpHost(Protocol):
    """What the HTTP surface reads of its server (``server.app.GameServer``)."""

    clients: set[Conn]
    limits: Limits
    lobby: Lobby
    origins: tuple[str, ...] | None
    store: ReplayStore | None
    recording_error: str | None
    web_dir: Path
    stats: dict[str, int]

    def stats_snapshot(self) -> dict[str, Any]: ...


class HttpSurface:
    """Answers a server's HTTP requests (websockets' ``process_request``)."""

    def __init__(self, srv: HttpHost) -> None:
        self.srv = srv

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

    async def process_request(self, connection: ServerConnection, request: Request
                               ) -> Response | None:
        # Split by hand: urlsplit reads "//host" as an authority and raises on "//[".
        path, _, query = request.path.partition("#")[0].partition("?")
        if path == "/ws":
            origin = request.headers.get("Origin")
            # Browsers always send Origin; other clients need not. The allow-list stops a
            # page on another site from using a visitor's browser to play or watch here.
            allowed = self.srv.origins
            if allowed is not None and origin is not None and origin not in allowed:
                self.srv.stats["refused_connections"] += 1
                return self._error(403, f"origin {origin[:100]!r} is not allowed here")
            if len(self.srv.clients) >= self.srv.limits.max_clients:
                self.srv.stats["refused_connections"] += 1
                return self._error(503, f"server full ({self.srv.limits.max_clients} connections)")
            return None
        try:
            if path == "/api/rooms":  # live state: read on the loop that changes it
                return self._json({"rooms": self.srv.lobby.listing()})
            if path == "/api/stats":
                if urllib.parse.parse_qs(query).get("reset") == ["1"]:
                    for room in self.srv.lobby.rooms.values():
                        room.sim.stats.lateness.clear()
                return self._json(self.srv.stats_snapshot())
            # Files and the index are read on a worker thread: the room loops go on.
            return await asyncio.to_thread(self._route, path, urllib.parse.parse_qs(query))
        except Exception:  # pragma: no cover - never take the server down on a request
            log.exception("HTTP %s failed", path)
            return self._error(500, "internal error")

    def _route(self, path: str, query: dict[str, list[str]]) -> Response:
        if path in ("/", "/index.html"):
            index = self.srv.web_dir / "index.html"
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
        if self.srv.store is None:
            return self._error(503, f"recording is off: {self.srv.recording_error}")

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
                "replays": self.srv.store.list(limit, offset, room, player=player, code=code),
                "total": self.srv.store.count(room, player=player, code=code),
            })
        rid = path[len("/api/replays/"):]
        if rid.endswith(".cbr"):
            rid = rid[:-4]
        p = self.srv.store.path_of(rid, code=code)
        if p is None:
            return self._error(404, f"no replay {rid[:100]!r}")
        return self._response(200, p.read_bytes(), "application/octet-stream", {
            "Content-Disposition": f'attachment; filename="{rid}.cbr"',
        })

    def _static(self, rel: str) -> Response:
        rel = urllib.parse.unquote(rel)
        root = self.srv.web_dir.resolve()
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

