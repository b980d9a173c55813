"""The game server's HTTP surface, on the websocket port (GET only):

* ``/`` the spectator page (``assets/web/index.html``, or a placeholder until it exists)
* ``/static/<path>`` files under ``assets/web/`` (no path traversal)
* ``/healthz`` ``ok`` once the rooms the server starts with can be joined; before (and
  while stopping) 503 ``starting``
* ``/api/rooms`` public rooms as JSON
* ``/api/replays`` recorded rounds as JSON (``?limit=&offset=&room=&player=&code=``)
* ``/api/replays/<id>`` one replay file (``game.wire.replay``; a private room's: ``?code=``),
  streamed from disk in chunks, one byte range of it with ``Range: bytes=A-B`` (206); with
  an index shared by hosts (``--db``), a 307 to the host that holds the file
* ``/api/stats`` the server's own counters (frame lateness, messages, CPU time, storage);
  ``?reset=1`` clears the frame lateness, only with the host's token
  (``Authorization: Bearer TOKEN``, the token in the data directory's ``host-token``)
* ``/metrics`` the same figures in the Prometheus text format (``server.metrics``)

and the admission of websocket upgrades on ``/ws`` (origin policy, connection limit). On a
host's engine (``clothball host --workers N``) its own loopback TCP port answers only its
bots' upgrades (``?house=``): everything else, 403 naming the public port.

A malformed request (a header that must come once given twice, or one that is not ASCII)
gets a 400 and one log line per address and minute
(``BadRequestLog``). Replay index queries run on their own few threads, a bounded number
waiting, rate-limited per address (``docs/security.md``); ``/healthz`` is answered on the
event loop and never waits behind them.

A download is written from the file in ``DOWNLOAD_CHUNK`` pieces, the next read only once
the socket has taken the last (asyncio's flow control): one costs the server at most a
chunk and the transport's buffer, whatever the file's size; ``Limits.max_downloads`` run
at once, and one whose client stops reading for ``Limits.download_stall_s`` is cut.
"""

from __future__ import annotations

import asyncio
import collections
import email.utils
import hmac
import http
import json
import logging
import mimetypes
import os
import re
import socket
import sqlite3
import time
import urllib.parse
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from websockets.asyncio.server import ServerConnection
from websockets.datastructures import Headers
from websockets.http11 import Request, Response

from ..game.wire.protocol import ProtocolError, check_text
from .conn import Conn, client_address
from .limits import Limits
from .lobby import Lobby
from .metrics import CONTENT_TYPE as METRICS_TYPE
from .metrics import exposition, registry_for
from .shared.bucket import TokenBucket
from .shared.osthread import name_os_thread
from .storage.index import IndexUnavailable, ReplayIndex

log = logging.getLogger("clothball.server")

PLACEHOLDER_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>clothball</title></head>
<body><h1>clothball</h1>
<p>The spectator page is not installed yet. Live rooms: <a href="/api/rooms">/api/rooms</a>,
recorded rounds: <a href="/api/replays">/api/replays</a>.</p></body></html>
"""


INDEX_THREADS = 2  # the replay index's own threads: SQLite reads
FILE_THREADS = 2  # the downloads' own threads: reads of one chunk each
DOWNLOAD_CHUNK = 64 * 1024  # bytes read from a replay file at a time
MAX_BUCKETS = 4096  # addresses whose index rate is remembered (the oldest forgotten first)
# Headers a request may carry once: two that disagree leave no right answer.
SINGLE_HEADERS = ("Host", "Origin", "Sec-WebSocket-Key", "Sec-WebSocket-Version", "Range",
                  "Content-Length")


class BadRequestLog:
    """Logs bad requests at a bounded rate: the first from an address in each ``window``
    seconds, at most ``max_lines`` lines a window in all; the rest are counted and logged
    as one line per address (and one for the others) when the next window starts."""

    def __init__(self, window: float = 60.0, max_lines: int = 20) -> None:
        self.window, self.max_lines = window, max_lines
        self.t0 = time.monotonic()
        self.logged: set[str] = set()
        self.more: collections.Counter[str] = collections.Counter()

    def note(self, address: str, level: int, msg: str, *args: object,
             exc_info: bool = False) -> None:
        now = time.monotonic()
        if now - self.t0 >= self.window:
            self.flush()
            self.t0 = now
        if address in self.logged or len(self.logged) >= self.max_lines:
            key = address if address in self.more or len(self.more) < self.max_lines \
                else "other addresses"
            self.more[key] += 1
            return
        self.logged.add(address)
        log.log(level, "%s: " + msg + " (more from there are counted)", address, *args,
                exc_info=exc_info)

    def flush(self) -> None:
        """Logs the counts of the window so far, and starts a new one."""
        for key, n in self.more.items():
            log.warning("%s: %d more bad requests in the last %.0f s", key, n,
                        time.monotonic() - self.t0)
        self.logged.clear()
        self.more.clear()


_RANGE_RE = re.compile(r"(\d{0,18})-(\d{0,18})")  # more digits than any file could need


class RangeError(ValueError):
    """A ``Range`` header that names no satisfiable part of the file (HTTP 416)."""


def parse_range(header: str | None, size: int) -> tuple[int, int] | None:
    """The first and last byte (inclusive) that ``Range: bytes=...`` asks of a ``size``-byte
    file: ``A-B``, ``A-`` (to the end) or ``-N`` (the last N). None: the whole file (no
    header, or a unit other than bytes, which a server ignores). ``RangeError`` naming the
    problem for a malformed or unsatisfiable range, or for several (one is served)."""
    if header is None:
        return None
    unit, sep, spec = header.strip().partition("=")
    if not sep or unit.strip().lower() != "bytes":
        return None
    parts = [p.strip() for p in spec.split(",")]
    if len(parts) != 1:
        raise RangeError("one byte range per request, e.g. Range: bytes=0-65535")
    m = _RANGE_RE.fullmatch(parts[0])
    if m is None or not (m[1] or m[2]):
        raise RangeError(f"Range {header.strip()[:80]!r} is not bytes=FIRST-LAST, "
                         "bytes=FIRST- or bytes=-LENGTH")
    if not m[1]:  # the last N bytes
        n = int(m[2])
        if n == 0 or size == 0:
            raise RangeError(f"Range {header.strip()[:80]!r} selects no byte of the "
                             f"{size}-byte file")
        return max(0, size - n), size - 1
    first = int(m[1])
    last = size - 1 if not m[2] else min(int(m[2]), size - 1)
    if m[2] and int(m[2]) < first:
        raise RangeError(f"Range {header.strip()[:80]!r}: the last byte is before the first")
    if first >= size:
        raise RangeError(f"Range {header.strip()[:80]!r} starts past the end of the "
                         f"{size}-byte file")
    return first, last


class _Download:
    """A replay file the index says the request may have (see ``HttpSurface._stream``)."""

    def __init__(self, path: Path, rid: str) -> None:
        self.path, self.rid = path, rid


@runtime_checkable
class Streaming(Protocol):
    """A connection whose handshake deadline a download may lift (``server.ws.Connection``)."""

    def no_handshake_deadline(self) -> None: ...


class HttpHost(Protocol):
    """What the HTTP surface reads of its server (``server.app.GameServer``)."""

    clients: set[Conn]
    per_address: collections.Counter[str]  # connections per client address
    limits: Limits
    lobby: Lobby
    origins: tuple[str, ...] | None
    port: int  # this process's own port
    public_port: int | None  # the gateways' port, where there are gateways
    engine_socket: Path | None  # the gateways' way in, where this is a host's engine
    ready: bool  # the rooms it starts with are open (GameServer.ready)
    store: ReplayIndex | None
    recording_error: str | None
    host_token: str
    house_key: str  # in the URL of the server's own bots (?house=)
    trusted_proxies: tuple[Any, ...]  # server.limits.parse_trusted_proxies
    web_dir: Path
    stats: dict[str, int]

    def stats_snapshot(self) -> dict[str, Any]: ...


class HttpSurface:
    """Answers a server's HTTP requests (websockets' ``process_request``)."""

    def __init__(self, srv: HttpHost) -> None:
        self.srv = srv
        self.bad = BadRequestLog()
        # Index queries get their own threads, so a flood of them cannot hold up files,
        # saves or anything else asyncio's default pool runs.
        self._pool = ThreadPoolExecutor(INDEX_THREADS, thread_name_prefix="replay-index",
                                        initializer=name_os_thread)
        self._files = ThreadPoolExecutor(FILE_THREADS, thread_name_prefix="replay-files",
                                         initializer=name_os_thread)
        self._waiting = 0
        self.downloads = 0  # under way now
        self._streams: set[asyncio.Transport] = set()  # their connections
        self._stopping = False
        self.download_bytes_held = 0  # read from files, not yet taken by a socket
        self.download_bytes_held_max = 0
        self._buckets: collections.OrderedDict[str, TokenBucket] = collections.OrderedDict()
        self._metrics = registry_for(srv.stats_snapshot)

    def abort_downloads(self) -> None:
        """The server is stopping: cut the downloads under way (a stalled one would hold
        the stop up for ``download_stall_s``) and start no more."""
        self._stopping = True
        for t in list(self._streams):
            t.abort()

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._files.shutdown(wait=True, cancel_futures=True)
        self.bad.flush()

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

    def _json(self, obj: Any, status: int = 200, extra: dict[str, str] | None = None
              ) -> Response:
        return self._response(status, json.dumps(obj, allow_nan=False).encode(),
                              "application/json", extra)

    def _error(self, status: int, message: str) -> Response:
        return self._json({"error": message, "status": status}, status)

    async def process_request(self, connection: ServerConnection, request: Request
                               ) -> Response | None:
        addr = connection.remote_address
        address = client_address(str(addr[0]) if addr else "?",
                                 request.headers.get("X-Forwarded-For"),
                                 self.srv.trusted_proxies)
        try:
            return await self._process(address, request, connection)
        except Exception:  # pragma: no cover - never take the server down on a request
            self.bad.note(address, logging.ERROR, "HTTP %s failed", request.path[:200],
                          exc_info=True)
            return self._error(500, "internal error")

    def _malformed(self, request: Request) -> str | None:
        """What makes ``request`` unanswerable, if anything."""
        for name in SINGLE_HEADERS:
            values = request.headers.get_all(name)
            if len(values) > 1:
                return f"the {name} header was sent more than once"
            # websockets reads header bytes as Latin-1: refuse what the server would read
            # wrongly (the target itself must be ASCII to be parsed at all).
            if values and not values[0].isascii():
                return f"the {name} header must be ASCII"
        return None

    def _house(self, query: str) -> bool:
        """The query carries the key of this server's own bots (compared in constant time)."""
        return hmac.compare_digest(
            urllib.parse.parse_qs(query).get("house", [""])[0].encode(),
            self.srv.house_key.encode())

    def _private(self, connection: ServerConnection) -> bool:
        """Whether ``connection`` came to a host engine's own TCP port (its bots', served
        by the engine's own gateway: the port its PROXY line names) rather than to the
        public port of its gateway processes."""
        return self.srv.engine_socket is not None and \
            getattr(connection, "local_port", None) == self.srv.port

    def _is_host(self, request: Request) -> bool:
        """The request carries the host's token (compared in constant time)."""
        scheme, _, token = request.headers.get("Authorization", "").partition(" ")
        return scheme.lower() == "bearer" and hmac.compare_digest(
            token.strip().encode(), self.srv.host_token.encode())

    def _origin_allowed(self, origin: str, host: str | None) -> bool:
        """The server's own pages (an Origin naming the host the request was sent to), and
        the ``--origin`` list (``*``: any)."""
        extra = self.srv.origins or ()
        if "*" in extra or origin in extra:
            return True
        scheme, _, netloc = origin.partition("://")
        if host is None or scheme not in ("http", "https"):
            return False
        return netloc.lower() == host.strip().lower()

    async def _process(self, address: str, request: Request, connection: ServerConnection
                       ) -> Response | None:
        problem = self._malformed(request)
        if problem is not None:
            self.bad.note(address, logging.WARNING, "bad request refused (%s)", problem)
            return self._error(400, problem)
        # Split by hand: urlsplit reads "//host" as an authority and raises on "//[".
        path, _, query = request.path.partition("#")[0].partition("?")
        if self._private(connection) and not (path == "/ws" and self._house(query)):
            # An engine's own TCP port is its bots' way in, nobody else's: a client there
            # would pass the gateways and their per-address limits (issue 40).
            return self._error(403, "this is a clothball engine's private port, for its "
                                    "own bots: connect to the host's public port "
                                    f"{self.srv.public_port}")
        if path == "/ws":
            origin = request.headers.get("Origin")
            # Browsers always send Origin; other clients need not. The policy stops a page
            # on another site from using a visitor's browser to play or watch here.
            if origin is not None and not self._origin_allowed(
                    origin, request.headers.get("Host")) and not self._a_hosts_page(origin):
                self.srv.stats["refused_connections"] += 1
                return self._error(403, f"origin {origin[:100]!r} is not allowed here (the "
                                        "host can allow it with --origin)")
            # What the connection handler needs (server.ws): who the client is, and whether
            # it is one of this server's own bots (bounded by rooms x seats, not counted).
            house = self._house(query)
            connection.client_address = address  # type: ignore[attr-defined]
            connection.house = house  # type: ignore[attr-defined]
            full = None if house else self.srv.limits.full_for(
                len(self.srv.clients), self.srv.per_address.get(address, 0))
            if full is not None:
                self.srv.stats["refused_connections"] += 1
                return self._error(503, full)
            return None
        if path == "/healthz":  # on the loop: never behind files or index queries
            if not self.srv.ready:  # listening already, its show room not yet open
                return self._response(503, b"starting\n", "text/plain; charset=utf-8")
            return self._response(200, b"ok\n", "text/plain; charset=utf-8")
        if path == "/api/rooms":  # live state: read on the loop that changes it
            self.srv.lobby.shown()
            msg = self.srv.lobby.rooms_message()
            del msg["type"]
            return self._json(msg)
        if path == "/api/stats":
            if "reset" in urllib.parse.parse_qs(query, keep_blank_values=True):
                if not self._is_host(request):
                    return self._error(403, "resetting the statistics needs the host's token: "
                                            "send Authorization: Bearer TOKEN, TOKEN from the "
                                            "file host-token in the server's data directory")
                for room in self.srv.lobby.rooms.values():
                    room.sim.stats.lateness.clear()
            return self._json(self.srv.stats_snapshot())
        if path == "/metrics":  # the same figures for Prometheus (server.metrics)
            return self._response(200, exposition(self._metrics), METRICS_TYPE)
        if path == "/api/replays" or path.startswith("/api/replays/"):
            found = await self._index_query(address, path, urllib.parse.parse_qs(query))
            if isinstance(found, _Download):
                return await self._stream(connection, request, found)
            return found
        # Files are read on a worker thread: the room loops go on.
        return await asyncio.to_thread(self._route, path)

    async def _index_query(self, address: str, path: str, query: dict[str, list[str]]
                           ) -> Response | _Download:
        """``_replays`` on the index's threads, if ``address`` is within its rate and the
        queue is not full."""
        lim = self.srv.limits
        bucket = self._buckets.pop(address, None) or TokenBucket(lim.index_rate, lim.index_burst)
        self._buckets[address] = bucket  # most recently used last
        if len(self._buckets) > MAX_BUCKETS:
            self._buckets.popitem(last=False)
        if not bucket.take():
            return self._error(429, f"at most {lim.index_rate:g} replay queries a second "
                                    "from one address; try again shortly")
        if self._waiting >= lim.index_queue:
            return self._error(503, "the replay index is busy; try again shortly")
        self._waiting += 1
        try:
            return await asyncio.get_running_loop().run_in_executor(
                self._pool, self._replays, path, query)
        finally:
            self._waiting -= 1

    def _a_hosts_page(self, origin: str) -> bool:
        """``origin`` is the page of a live host of this one's cluster (its advertised
        address): a page that followed a redirect here from the host that served it."""
        peers = self.srv.lobby.peers
        scheme, _, netloc = origin.lower().partition("://")
        if peers is None or scheme not in ("http", "https"):
            return False
        return any(urllib.parse.urlsplit(h.address).netloc.lower() == netloc
                   for h in peers.hosts.values())

    def _route(self, path: str) -> Response:
        if path in ("/", "/index.html"):
            index = self.srv.web_dir / "index.html"
            if index.is_file():
                return self._response(200, index.read_bytes(), "text/html; charset=utf-8")
            return self._response(200, PLACEHOLDER_PAGE.encode(), "text/html; charset=utf-8")
        if path.startswith("/static/"):
            return self._static(path[len("/static/"):])
        return self._error(404, f"no such path {path[:200]!r}")

    def _replays(self, path: str, query: dict[str, list[str]]) -> Response | _Download:
        store = self.srv.store
        if store is None:
            return self._error(503, f"recording is off: {self.srv.recording_error}")
        try:
            return self._replays_of(store, path, query)
        except (sqlite3.Error, IndexUnavailable) as e:
            # The index was closed under this query (the data directory's problem is being
            # acted on: server.storage.datadir.Storage), the disk failed a read, or a shared index's
            # PostgreSQL is away.
            return self._error(503, f"the replay index cannot be read now ({e}); try again "
                                    "shortly")

    def _replays_of(self, store: ReplayIndex, path: str, query: dict[str, list[str]]
                    ) -> Response | _Download:

        def one(key: str, max_len: int = 64) -> str | None:
            v = query.get(key, [None])[0]
            return None if v is None else check_text(key, v, max_len)

        try:  # the same checks as the websocket's fields: a player's name matches its own
            room, player, code = one("room"), one("player", 32), one("code")
            limit = min(1000, max(1, int(query.get("limit", ["100"])[0])))
            offset = min(2**62, max(0, int(query.get("offset", ["0"])[0])))
        except ProtocolError as e:
            return self._error(400, e.message)
        except ValueError:
            return self._error(400, "limit and offset must be whole numbers")
        if path == "/api/replays":
            return self._json({
                "replays": store.list(limit, offset, room, player=player, code=code),
                "total": store.count(room, player=player, code=code),
            })
        rid = path[len("/api/replays/"):]
        if rid.endswith(".cbr"):
            rid = rid[:-4]
        p = store.locate(rid, code=code)
        if p is None:
            return self._error(404, f"no replay {rid[:100]!r}")
        if isinstance(p, str):
            # A shared index's round whose file another host holds: the client asks there.
            return self._response(307, b"", "text/plain; charset=utf-8",
                                  {"Location": p, "Access-Control-Allow-Origin": "*"})
        return _Download(p, rid)

    async def _stream(self, connection: ServerConnection, request: Request, dl: _Download
                      ) -> Response:
        """Writes the file (or the ``Range`` asked for) to the connection in chunks, then
        closes it; the returned response is then never sent (the connection is closed)."""
        lim = self.srv.limits
        if self._stopping:
            return self._error(503, "the server is stopping")
        if self.downloads >= lim.max_downloads:
            return self._error(503, f"{lim.max_downloads} downloads are under way (the "
                                    "limit); try again shortly")
        loop = asyncio.get_running_loop()
        self.downloads += 1  # counted before the first wait: the limit holds
        try:
            # Open now: a round pruned while it is being sent stays readable to the end.
            fd = await loop.run_in_executor(self._files, os.open, dl.path, os.O_RDONLY)
        except FileNotFoundError:
            self.downloads -= 1
            return self._error(404, f"no replay {dl.rid!r}")
        except BaseException:
            self.downloads -= 1
            raise
        try:
            size = os.fstat(fd).st_size
            try:
                span = parse_range(request.headers.get("Range"), size)
            except RangeError as e:
                return self._json({"error": str(e), "status": 416}, 416,
                                  {"Content-Range": f"bytes */{size}"})
            first, last = span if span is not None else (0, size - 1)
            # Any page may read it (a cluster's page fetches it from another host after a
            # redirect); a private round needs its code in the URL all the same.
            head = [("Content-Length", str(last - first + 1)),
                    ("Content-Type", "application/octet-stream"),
                    ("Access-Control-Allow-Origin", "*"),
                    ("Content-Disposition", f'attachment; filename="{dl.rid}.cbr"'),
                    ("Accept-Ranges", "bytes")]
            status = http.HTTPStatus.OK
            if span is not None:
                status = http.HTTPStatus.PARTIAL_CONTENT
                head.append(("Content-Range", f"bytes {first}-{last}/{size}"))
            await self._send_file(connection, status, head, fd, first, last + 1)
        finally:
            self.downloads -= 1
            os.close(fd)
        # Never sent: websockets answers only a connection still in its handshake.
        return self._response(200, b"", "application/octet-stream")

    async def _send_file(self, connection: ServerConnection, status: http.HTTPStatus,
                         head: list[tuple[str, str]], fd: int, start: int, end: int) -> None:
        transport = connection.transport
        self._streams.add(transport)
        try:
            await self._write_file(connection, transport, status, head, fd, start, end)
        finally:
            self._streams.discard(transport)

    async def _write_file(self, connection: ServerConnection, transport: asyncio.Transport,
                          status: http.HTTPStatus, head: list[tuple[str, str]], fd: int,
                          start: int, end: int) -> None:
        stall = self.srv.limits.download_stall_s
        if isinstance(connection, Streaming):
            connection.no_handshake_deadline()  # a long file may take longer than a handshake
        sock = transport.get_extra_info("socket")
        if sock is not None:  # as for websocket clients: a bounded kernel buffer
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF,
                                self.srv.limits.socket_send_buffer)
            except OSError:  # pragma: no cover - not settable on this platform
                pass
        headers = Headers([("Date", email.utils.formatdate(usegmt=True)),
                           ("Connection", "close"), ("Cache-Control", "no-store"),
                           ("X-Content-Type-Options", "nosniff"), *head])
        transport.write(f"HTTP/1.1 {status.value} {status.phrase}\r\n".encode()
                        + headers.serialize())
        loop = asyncio.get_running_loop()
        pos = start
        try:
            while pos < end and not transport.is_closing():
                chunk = await loop.run_in_executor(
                    self._files, os.pread, fd, min(DOWNLOAD_CHUNK, end - pos), pos)
                if not chunk:  # the file shrank under us: the client sees a short body
                    break
                pos += len(chunk)
                self._held(len(chunk))
                try:
                    if transport.is_closing():
                        break
                    transport.write(chunk)
                    # Wait until the socket has taken it before the next read.
                    await asyncio.wait_for(connection.drain(), stall)
                finally:
                    self._held(-len(chunk))
        except (TimeoutError, ConnectionError):
            transport.abort()  # a client that stopped reading holds nothing longer
        transport.close()
        try:
            await asyncio.wait_for(asyncio.shield(connection.connection_lost_waiter), stall)
        except TimeoutError:
            transport.abort()
            await asyncio.shield(connection.connection_lost_waiter)

    def _held(self, n: int) -> None:
        self.download_bytes_held += n
        self.download_bytes_held_max = max(self.download_bytes_held_max,
                                           self.download_bytes_held)

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

