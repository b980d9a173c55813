"""A reusable asyncio client of the clothball server (players, spectators, bots, tools).

::

    client = await NetClient.connect("ws://127.0.0.1:8765/ws", name="ann", role="player")
    client.reach                      # the box this seat's hand may move in
    await client.send_hip(h)          # latest wins on the server
    client.corner_state()             # newest CORNER as a devices.base.CornerState
    client.mesh                       # newest MESH (spectators and renderers)
    msg = await client.wait_event("score", timeout=30)
    await client.close()

The client keeps only the newest CORNER and MESH (a slow consumer sees the latest state,
never a backlog) and a bounded history of JSON messages. ``request`` sends a control
message with an ``id`` and waits for the reply that echoes it (``ServerError`` on an error
reply). See ``docs/protocol.md``.

A client sent to another process or host for its room (a ``redirect``) whose connection
there is lost (that host died) goes back to the lobby where it first connected (``home``)
and receives ``{"type": "host_gone", "room", "url", "message"}`` (a message of its own,
not the server's), saying which room's host went away.
"""

from __future__ import annotations

import asyncio
import collections
import itertools
import json
import math
import socket
import ssl
import time
import urllib.parse
from collections.abc import Callable
from typing import Any

import numpy as np
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus

from ..devices.base import CornerState, Reach
from ..wire import protocol as P
from .tap import TapConnection

HISTORY = 2000
MAX_REDIRECTS = 3  # hops a request may be sent on (a room lives on one process or host)
# How a connection ends when its server goes away: no close frame (1006, the process died;
# None before websockets sets it) or "going away" (1001, it stopped). Other codes are the
# server's word about this client (replaced, refused): no host went away.
HOST_GONE_CODES = (None, 1001, 1006)


class _Connection(TapConnection, ClientConnection):
    """The client's connection: CORNER and MESH messages go straight to ``on_binary``
    (see ``game.net.tap``)."""


class ServerError(RuntimeError):
    """The server answered with an error message (``code`` as in ``protocol.ERROR_CODES``)."""

    def __init__(self, msg: dict[str, Any]) -> None:
        super().__init__(f"{msg.get('code')}: {msg.get('message')}")
        self.code = str(msg.get("code"))
        self.message = str(msg.get("message"))
        self.reply = msg


def explain_connect_error(url: str, e: BaseException) -> tuple[str, bool]:
    """Why connecting to ``url`` failed, in one line that says what to do, and whether
    trying again later may help (a server not up yet) or not (a wrong address, a version
    mismatch, a refusal)."""
    parts = urllib.parse.urlsplit(url)
    where = parts.netloc or url
    fix_url = f"ws://{parts.netloc}/ws"
    if isinstance(e, ServerError):
        if e.code == "bad_version":
            return (f"version mismatch: this client speaks protocol {P.PROTOCOL_VERSION}, the "
                    f"server says \"{e.message}\"; play with the clothball version it runs",
                    False)
        return f"the server refused: {e.message} ({e.code})", e.code == "server_busy"
    if isinstance(e, ConnectionRefusedError):
        return (f"nothing is listening at {where} (connection refused): start one with "
                "'clothball host', or check --server", True)
    if isinstance(e, socket.gaierror):
        return f"unknown host {parts.hostname!r}: check the address given to --server", False
    if isinstance(e, ssl.SSLError) or (parts.scheme == "wss" and isinstance(
            e, ConnectionResetError | EOFError)):  # a plain server drops a TLS hello
        return (f"{where} does not speak TLS (wss://): try {fix_url}", False)
    if isinstance(e, TimeoutError):
        return (f"no answer from {where} in time: is the server up, and is the port "
                "open in the firewall?", True)
    if isinstance(e, InvalidStatus):
        status = e.response.status_code
        body = bytes(e.response.body or b"").decode("utf-8", "replace").strip()
        try:  # the game server's refusals are {"error": why}
            body = str(json.loads(body)["error"])
        except (ValueError, TypeError, KeyError):
            pass
        if status in (403, 503) and body:
            return f"the server refused: {body[:160]} (HTTP {status})", status == 503
        return (f"no game at {url} (HTTP {status}): the game's address is {fix_url}",
                False)
    if isinstance(e, InvalidHandshake):
        scheme = "ws://" if parts.scheme == "wss" else "wss://"
        return (f"{where} is not a clothball websocket ({e}): check the address, or try "
                f"{scheme}", False)
    if isinstance(e, ConnectionError) and "closed" in str(e):
        return f"the server closed the connection: {e}", True
    if isinstance(e, OSError):
        why = e.strerror or str(e) or type(e).__name__
        return f"cannot reach {where}: {why}; check the network and --server", True
    return f"cannot connect to {url}: {e}", False


async def _open(url: str, timeout: float) -> ClientConnection:
    return await asyncio.wait_for(
        connect(url, max_size=2**24, compression=None, open_timeout=timeout,
                create_connection=_Connection), timeout)


class NetClient:
    """A connected client. Create with ``await NetClient.connect(...)``."""

    def __init__(self, ws: ClientConnection, clock: Callable[[], float] = time.perf_counter,
                 record_latency: bool = False, history: int = HISTORY) -> None:
        self.ws = ws
        self.clock = clock
        self.welcome: dict[str, Any] = {}
        self.joined: dict[str, Any] | None = None
        self._corner: P.Corner | None = None
        self._corner_raw: bytes | None = None  # newest CORNER, decoded when first asked for
        self.corner_received_at = 0.0
        self.mesh: P.Mesh | None = None
        self.mesh_raw: bytes | None = None
        self.decode_mesh = True
        # The newest JSON messages (``history`` of them: the server's own bots keep few, as
        # they run inside it and every room's state message is a kilobyte or two).
        self.messages: collections.deque[dict[str, Any]] = collections.deque(maxlen=history)
        self.received_total = 0  # JSON messages ever received (history index base)
        self.counts = {"corner": 0, "mesh": 0, "json": 0, "bad": 0}
        # When the newest MESH messages came (bounded: a client may watch for hours).
        self.mesh_times: collections.deque[float] = collections.deque(maxlen=HISTORY)
        self.record_latency = record_latency
        self.latencies: list[float] = []  # s, HIP sent -> CORNER that applied it received
        self.on_corner: Callable[[P.Corner], None] | None = None
        self.on_mesh: Callable[[bytes], None] | None = None
        self.on_message: Callable[[dict[str, Any]], None] | None = None
        self._last_echo = 0
        self._hip_seq = 0
        self._ids = itertools.count(1)
        self._pending: dict[Any, asyncio.Future[dict[str, Any]]] = {}
        self._changed = asyncio.Condition()
        self._reader: asyncio.Task[None] | None = None
        self.close_code: int | None = None
        self.close_reason = ""
        self.name = "player"
        self.url = ""
        self.home = ""  # where this client first connected (its lobby if a host goes away)
        self.host_gone: dict[str, Any] | None = None  # the newest host_gone message
        self._closing = False
        self._gone: asyncio.Task[None] | None = None

    # --- connecting -----------------------------------------------------------------------
    @classmethod
    async def connect(cls, url: str, *, name: str = "player", role: str = "lobby",
                      room: str | None = None, seat: int | None = None, code: str | None = None,
                      token: str | None = None, corner_rate: float | None = None,
                      mesh: bool | None = None, timeout: float = 10.0,
                      record_latency: bool = False, decode_mesh: bool = True,
                      history: int = HISTORY, _hops: int = 0, _home: str | None = None,
                      **extra: Any) -> NetClient:
        """Open a connection, say hello and, for a player or spectator, join ``room``.
        A join the server redirects (the room lives on another process or host) is made
        there, on a new connection."""
        ws = await _open(url, timeout)
        client = cls(ws, record_latency=record_latency, history=history)
        client.decode_mesh = decode_mesh
        client.name, client.url, client.home = name, url, _home or url
        client._reader = asyncio.create_task(client._read())
        hello: dict[str, Any] = {"type": "hello", "version": P.PROTOCOL_VERSION, "name": name,
                                 "role": role, "id": 0, **extra}
        for k, v in (("room", room), ("seat", seat), ("code", code), ("token", token),
                     ("corner_rate", corner_rate), ("mesh", mesh)):
            if v is not None:
                hello[k] = v
        try:
            start = client.received_total
            await client.send_json(hello)
            client.welcome = await client.wait_for(
                lambda m: m["type"] in ("welcome", "error"), timeout, since=start)
            if client.welcome["type"] == "error":
                raise ServerError(client.welcome)
            if role != "lobby" or token is not None:
                reply = await client.wait_for(
                    lambda m: m["type"] in ("joined", "error", "redirect") and m.get("re") == 0,
                    timeout, since=start)
                if reply["type"] == "error":
                    raise ServerError(reply)
                if reply["type"] == "redirect":
                    await client.close()
                    if _hops >= MAX_REDIRECTS:
                        raise ConnectionError(f"too many redirects (last: {reply['url']})")
                    return await cls.connect(
                        str(reply["url"]), name=name, role=role, room=room, seat=seat,
                        code=code, token=token, corner_rate=corner_rate, mesh=mesh,
                        timeout=timeout, record_latency=record_latency,
                        decode_mesh=decode_mesh, history=history, _hops=_hops + 1,
                        _home=client.home, **extra)
                client.joined = reply
        except BaseException:
            await client.close()
            raise
        return client

    async def _move(self, url: str, timeout: float) -> None:
        """Follow a redirect: this client, now connected to ``url`` (the process that
        hosts the room), in its lobby; the old connection is closed."""
        ws = await _open(url, timeout)
        old, old_reader = self.ws, self._reader
        self.ws, self.url = ws, url
        self._reader = asyncio.create_task(self._read())
        await old.close()
        if old_reader is not None:
            await asyncio.gather(old_reader, return_exceptions=True)
        start = self.received_total
        await self.send_json({"type": "hello", "version": P.PROTOCOL_VERSION,
                              "name": self.name, "id": 0})
        welcome = await self.wait_for(lambda m: m["type"] in ("welcome", "error"), timeout,
                                      since=start)
        if welcome["type"] == "error":
            raise ServerError(welcome)
        self.welcome = welcome

    # --- properties -----------------------------------------------------------------------
    @property
    def corner(self) -> P.Corner | None:
        """The newest CORNER message (decoded on first access: a 1 kHz stream is mostly
        superseded before anyone looks)."""
        if self._corner is None and self._corner_raw is not None:
            self._corner = P.decode_corner(self._corner_raw)
        return self._corner

    @corner.setter
    def corner(self, value: P.Corner | None) -> None:
        self._corner, self._corner_raw = value, None

    @property
    def seat(self) -> int | None:
        return None if self.joined is None else self.joined.get("seat")

    @property
    def token(self) -> str | None:
        return None if self.joined is None else self.joined.get("token")

    @property
    def room(self) -> str | None:
        return None if self.joined is None else self.joined.get("room")

    @property
    def geometry(self) -> dict[str, Any]:
        return {} if self.joined is None else self.joined["geometry"]

    @property
    def reach(self) -> Reach | None:
        if self.joined is None or "reach" not in self.joined:
            return None
        r = self.joined["reach"]
        return Reach(np.array(r["centre"], dtype=np.float64),
                     np.array(r["half_extent"], dtype=np.float64))

    def corner_state(self) -> CornerState | None:
        c = self.corner
        if c is None:
            return None
        return CornerState(position=c.position, velocity=c.velocity, force=c.force,
                           stiffness=c.stiffness, frame=c.frame, server_time=c.server_time,
                           received_at=self.corner_received_at)

    # --- sending --------------------------------------------------------------------------
    async def send_json(self, msg: dict[str, Any]) -> None:
        await self.ws.send(P.encode_json(msg))

    async def request(self, type_: str, timeout: float = 10.0, **fields: Any) -> dict[str, Any]:
        """Send a control message and wait for its reply (``ServerError`` on an error).
        A ``redirect`` reply (the room lives on another process or host) moves this client
        there and sends the request again."""
        for _hop in range(MAX_REDIRECTS + 1):
            rid = next(self._ids)
            fut: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
            self._pending[rid] = fut
            try:
                await self.send_json({"type": type_, "id": rid, **fields})
                reply = await asyncio.wait_for(fut, timeout)
            finally:
                self._pending.pop(rid, None)
            if reply["type"] != "redirect":
                break
            await self._move(str(reply["url"]), timeout)
            fields = {**fields, **(reply.get("with") or {})}
        else:
            raise ConnectionError(f"too many redirects for {type_!r} (last: {reply['url']})")
        if reply["type"] == "error":
            raise ServerError(reply)
        if reply["type"] == "joined":
            self.joined = reply
        return reply

    async def send_hip(self, position: Any) -> None:
        """Send the hand position (world metres); the server keeps only the newest."""
        self._hip_seq = (self._hip_seq + 1) & 0xFFFFFFFF
        data = P.encode_hip(position, self._hip_seq, self.clock())
        # A HIP stream at 1 kHz spent most of its time in ws.send's context manager.
        ws = self.ws
        if not (isinstance(ws, TapConnection) and ws.send_now(data)):
            await ws.send(data)

    async def join(self, room: str, role: str = "player", **fields: Any) -> dict[str, Any]:
        return await self.request("join", room=room, role=role, **fields)

    # --- receiving ------------------------------------------------------------------------
    async def _read(self) -> None:
        ws = self.ws  # this reader's connection (a redirect gives the client a new one)
        if isinstance(ws, _Connection):
            ws.listen(self._on_binary)
        try:
            async for message in ws:
                if isinstance(ws, _Connection):
                    ws.message_read()
                if isinstance(message, bytes):
                    self._on_binary(message)
                else:
                    await self._on_text(message)
        except ConnectionClosed:
            pass
        finally:
            if isinstance(ws, _Connection):
                ws.listen(None)
            if ws is self.ws:  # else moved on: the client lives on, on its new connection
                self.close_code, self.close_reason = ws.close_code, ws.close_reason or ""
                for fut in self._pending.values():
                    if not fut.done():
                        fut.set_exception(ConnectionError("connection closed"))
                if (not self._closing and self.url != self.home and self.room is not None
                        and ws.close_code in HOST_GONE_CODES):
                    # The host of the room this client was sent to went away: back to the
                    # lobby it came from (waiters wait for that rather than fail).
                    self._reader = None
                    self._gone = asyncio.create_task(self._host_went_away(self.room, self.url))
                async with self._changed:
                    self._changed.notify_all()

    async def _host_went_away(self, room: str, url: str) -> None:
        self.joined = None
        where = f"the host of room {room} went away ({url})"
        msg: dict[str, Any] = {"type": "host_gone", "room": room, "url": url,
                               "message": f"{where}; back in the lobby at {self.home}"}
        try:
            await self._move(self.home, 10.0)
        except (OSError, TimeoutError, ConnectionError, ServerError) as e:
            msg["message"] = f"{where}; the lobby at {self.home} cannot be reached either: {e}"
        self.host_gone = msg
        self.messages.append(msg)
        self.received_total += 1
        if self.on_message is not None:
            self.on_message(msg)
        async with self._changed:
            self._changed.notify_all()

    def _on_binary(self, data: bytes) -> None:
        now = self.clock()
        kind = data[0] if data else 0
        try:
            if kind == P.CORNER:
                # Checked as decode_corner checks it (it raises on anything else); the
                # message is decoded when it is asked for.
                if len(data) != P.CORNER_SIZE:
                    P.decode_corner(data)
                v = P.CORNER_MSG.unpack(data)
                if v[1] != P.PROTOCOL_VERSION or not math.isfinite(v[4]):
                    P.decode_corner(data)
                self._corner, self._corner_raw = None, data
                self.corner_received_at = now
                self.counts["corner"] += 1
                hip_seq, hip_time = v[-2], v[-1]
                if self.record_latency and hip_seq != self._last_echo:
                    self._last_echo = hip_seq
                    if math.isfinite(hip_time):
                        self.latencies.append(now - hip_time)
                if self.on_corner is not None:
                    self.on_corner(self.corner)
            elif kind == P.MESH:
                self.counts["mesh"] += 1
                self.mesh_times.append(now)
                self.mesh_raw = data
                if self.decode_mesh:
                    self.mesh = P.decode_mesh(data)
                if self.on_mesh is not None:
                    self.on_mesh(data)
            else:
                self.counts["bad"] += 1
        except P.ProtocolError:
            self.counts["bad"] += 1

    async def _on_text(self, text: str) -> None:
        try:
            msg = P.decode_json(text, limit=2**24)
        except P.ProtocolError:
            self.counts["bad"] += 1
            return
        self.counts["json"] += 1
        self.messages.append(msg)
        self.received_total += 1
        re = msg.get("re")
        if re is not None and re in self._pending and msg["type"] != "welcome":
            fut = self._pending[re]
            if not fut.done():
                fut.set_result(msg)
        if self.on_message is not None:
            self.on_message(msg)
        async with self._changed:
            self._changed.notify_all()

    async def wait_for(self, predicate: Callable[[dict[str, Any]], bool], timeout: float = 10.0,
                       since: int | None = None) -> dict[str, Any]:
        """The first JSON message (received at or after history index ``since``; default:
        from now on) for which ``predicate`` is true."""
        start = self.received_total if since is None else since

        def find() -> dict[str, Any] | None:
            first = self.received_total - len(self.messages)
            for i, m in enumerate(self.messages):
                if first + i >= start and predicate(m):
                    return m
            return None

        async def waiter() -> dict[str, Any]:
            async with self._changed:
                while True:
                    m = find()
                    if m is not None:
                        return m
                    task = self._live_task()
                    if task is not None and task.done():
                        raise ConnectionError(
                            f"connection closed ({self.close_code} {self.close_reason})")
                    await self._changed.wait()

        return await asyncio.wait_for(waiter(), timeout)

    async def wait_event(self, event: str, timeout: float = 10.0, since: int | None = None,
                         **match: Any) -> dict[str, Any]:
        """The next ``{"type": "event", "event": event}`` whose fields equal ``match``."""
        return await self.wait_for(
            lambda m: m.get("type") == "event" and m.get("event") == event
            and all(m.get(k) == v for k, v in match.items()),
            timeout, since,
        )

    def _live_task(self) -> asyncio.Task[None] | None:
        """What keeps this client going: its reader, or while a host gone away is left,
        that move (``_host_went_away``)."""
        return self._reader if self._reader is not None else self._gone

    async def wait_closed(self, timeout: float = 10.0) -> None:
        """Until the connection is closed for good: a redirect's or a gone host's move to
        another connection is waited through."""
        async def waiting() -> None:
            while True:
                task = self._live_task()
                if task is None:
                    return
                await asyncio.shield(task)
                if self._live_task() is task:
                    return  # it ended and nothing took over

        await asyncio.wait_for(waiting(), timeout)

    async def close(self) -> None:
        self._closing = True
        if self._gone is not None and not self._gone.done():
            self._gone.cancel()
            await asyncio.gather(self._gone, return_exceptions=True)
        await self.ws.close()
        if self._reader is not None:
            try:
                await asyncio.wait_for(self._reader, 5.0)
            except (TimeoutError, asyncio.CancelledError):
                self._reader.cancel()
