"""The game server's websocket endpoint ``/ws``: one task per connection reads its
messages; the first must be a ``hello``, then control messages (JSON) go through a table of
handlers and binary ones (HIPs) straight to the player's room.

Handlers are thin: they parse, check and hand over to the lobby and the rooms, and every bad
message gets a JSON error while the room runs on. What a client may do is bounded by
``server.limits.Limits`` (``docs/security.md``); the protocol is ``docs/protocol.md``.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import socket
import time
import urllib.parse
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any, Protocol

from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed

from ..game.net.tap import TapConnection
from ..game.wire import protocol as P
from ..game.wire.protocol import ProtocolError
from .conn import Conn
from .directory import IO_TIMEOUT_S, Moved, NotInView
from .limits import Limits
from .lobby import Lobby, parse_settings
from .room import Room
from .shared import proxyline

log = logging.getLogger("clothball.server")


OPEN_TIMEOUT_S = 10.0  # for the request and its answer (websockets' open_timeout)


class Connection(TapConnection, ServerConnection):
    """The server's connection: HIPs go straight to ``on_binary`` once the handler has set
    it, when it starts its read loop (see ``game.net.tap``).

    Its opening handshake (the HTTP request and its answer) has ``OPEN_TIMEOUT_S``, which
    a replay download lifts (``no_handshake_deadline``): it is bounded by its own stall
    timeout instead (``server.http``). The server is started with ``open_timeout=None``."""

    _deadline: asyncio.Timeout | None = None

    async def handshake(self, *args: Any, **kwargs: Any) -> None:
        async with asyncio.timeout(OPEN_TIMEOUT_S) as self._deadline:
            await super().handshake(*args, **kwargs)

    def no_handshake_deadline(self) -> None:
        if self._deadline is not None:
            self._deadline.reschedule(None)

    # A connection from a gateway (the engine's Unix socket) opens with a PROXY line
    # naming the client (server.shared.proxyline): read before the protocol sees a byte,
    # it is the connection's remote address, so limits and logs name the client.
    _line: bytearray | None = None
    _peer: tuple[str, int] | None = None
    lanes = False  # the gateway serves this client's lane (server.shared.lanes)
    local_port: int | None = None  # the port the client connected to (its PROXY line's)

    def connection_made(self, transport: Any) -> None:
        super().connection_made(transport)
        sock = transport.get_extra_info("socket")
        if sock is not None and sock.family == socket.AF_UNIX:
            self._line = bytearray()

    def data_received(self, data: bytes) -> None:
        line = self._line
        if line is None:
            super().data_received(data)
            return
        end = data.find(b"\n")
        line += data if end < 0 else data[:end + 1]
        if end < 0 and len(line) < proxyline.MAX_LINE:
            return
        try:
            self._peer = proxyline.decode(bytes(line))
            self.lanes = proxyline.lanes(bytes(line))
            self.local_port = proxyline.local_port(bytes(line))
        except proxyline.BadLine as e:
            log.warning("gateway connection refused: %s", e)
            self.stream.abort()
            return
        self._line = None
        if end + 1 < len(data):
            super().data_received(data[end + 1:])

    @property
    def remote_address(self) -> Any:
        if self._peer is not None:
            return self._peer
        return super().remote_address


JOIN_ROLES = ("player", "spectator")


def hello_joins(msg: dict[str, Any]) -> bool:
    """Whether a hello also joins a room (a role other than ``lobby``, or a ``token``); a
    hello whose role is none of the three, or that names a player's or spectator's role
    without a ``room`` (or a ``token``), is refused: it cannot be welcomed as asked."""
    role = P.field_str(msg, "role", "lobby", max_len=16)
    if role != "lobby" and role not in JOIN_ROLES:
        raise ProtocolError("bad_message", f"'role': must be 'lobby', 'player' or "
                            f"'spectator', got {role!r}")
    if role != "lobby" and msg.get("room") is None and msg.get("token") is None:
        raise ProtocolError("bad_message", f"missing field 'room': a hello with role "
                            f"{role!r} joins a room (or send a 'token' to resume a seat)")
    return role != "lobby" or "token" in msg


@dataclass
class Later:
    """A handler's reply that waits, that connection alone, for ``wait`` (a new room's
    publication to the shared directory), then is ``reply()``."""

    wait: Awaitable[Any]
    reply: Callable[[], dict[str, Any] | None]


Reply = dict[str, Any] | Later | None  # what a handler returns


def token_room(token: str) -> str | None:
    """The room a reconnect token was given in (``Room._new_token``: id, dot, secret);
    None for a token of another form."""
    room_id, dot, _ = token.rpartition(".")
    return room_id if dot and room_id else None


class WsHost(Protocol):
    """What the endpoint uses of its server (``server.app.GameServer``)."""

    clients: set[Conn]
    per_address: collections.Counter[str]
    limits: Limits
    lobby: Lobby
    scenes: dict[str, Any]
    epoch: float
    stats: dict[str, int]


class WsEndpoint:
    """Serves a server's websocket connections (websockets' connection handler)."""

    def __init__(self, srv: WsHost) -> None:
        self.srv = srv
        self.handlers: dict[str, Callable[[Conn, dict[str, Any]], Reply]] = {
            "hello": self._msg_hello,
            "ping": self._msg_ping,
            "list_rooms": self._msg_list_rooms,
            "create_room": self._msg_create_room,
            "join": self._msg_join,
            "leave": self._msg_leave,
            "ready": self._msg_ready,
            "start": self._msg_start,
            "add_bot": self._msg_add_bot,
            "remove_bot": self._msg_remove_bot,
            "state": self._msg_state,
        }

    async def handler(self, ws: ServerConnection) -> None:
        # The client's address (forwarded by a trusted proxy) and whether it is one of the
        # server's own bots: what server.http found at the upgrade.
        conn = Conn(ws, self.srv.limits, address=getattr(ws, "client_address", None),
                    house=getattr(ws, "house", False),
                    own_gateway=getattr(ws, "local_port", None) == self.srv.port)
        self.srv.clients.add(conn)
        sock = conn.transport.get_extra_info("socket") if conn.transport is not None else None
        if sock is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF,
                                self.srv.limits.socket_send_buffer)
            except OSError:  # pragma: no cover - not settable on this platform
                pass
        counted = not conn.house  # the server's own bots take no address's slots
        if counted:
            self.srv.per_address[conn.address] += 1
        try:
            if counted and \
                    self.srv.per_address[conn.address] > self.srv.limits.conns_per_address:
                self.srv.stats["refused_connections"] += 1
                await ws.close(1008, f"too many connections from {conn.address} (limit "
                                     f"{self.srv.limits.conns_per_address})")
                return
            timeout = self.srv.limits.hello_timeout
            try:
                first = await asyncio.wait_for(ws.recv(), timeout)
                if isinstance(ws, Connection):
                    ws.message_read()
            except TimeoutError:
                conn.error("bad_message", f"no hello within {timeout:g} s")
                await asyncio.sleep(0.05)
                await ws.close(1008, "no hello")
                return
            if not await self._hello(conn, first):
                await asyncio.sleep(0.05)  # let the error go out first
                await ws.close(1008, "hello refused")
                return
            if isinstance(ws, Connection):
                ws.listen(lambda data: self._on_binary_now(conn, data),
                          self.srv.limits.max_message_bytes)
            async for message in ws:
                if isinstance(ws, Connection):
                    ws.message_read()
                self.srv.stats["messages_in"] += 1
                conn.received += 1
                if isinstance(message, bytes):
                    self._on_binary(conn, message)
                else:
                    waiting = self._on_text(conn, message)
                    if waiting is not None:  # the directory: this client's next message waits
                        await waiting
                if conn.closed:
                    break
        except ConnectionClosed:
            pass
        finally:
            if isinstance(ws, Connection):
                ws.listen(None)
            self.srv.clients.discard(conn)
            if counted:
                self.srv.per_address[conn.address] -= 1
                if self.srv.per_address[conn.address] <= 0:
                    del self.srv.per_address[conn.address]
            if conn.room is not None:
                conn.room.disconnected(conn)
            self.srv.stats["messages_out"] += conn.sent
            await conn.finish()

    async def sweep_idle(self) -> None:
        """Closes lobby connections that have sent no request (pings and binary messages do
        not count) for ``Limits.lobby_idle_s`` (1008, saying so), so that idle clients
        cannot hold the server's slots; players and spectators are not idle in this sense
        (they watch). Drops a client one of whose messages has waited on its socket past
        ``Limits.slow_drop_s``. Runs until the server stops."""
        while True:
            limit = self.srv.limits.lobby_idle_s
            await asyncio.sleep(min(5.0, limit / 4, self.srv.limits.slow_drop_s / 2))
            now = time.monotonic()
            for c in list(self.srv.clients):
                if c.stuck():
                    continue
                if c.role == "lobby" and c.hello_done and now - c.last_in > limit:
                    c.drop(f"idle: no request but pings for {limit:g} s in the lobby")

    async def _hello(self, conn: Conn, first: str | bytes) -> bool:
        """The first message must be a hello. True when the connection may go on."""
        try:
            if isinstance(first, bytes):
                raise ProtocolError("bad_message", "the first message must be a JSON hello")
            msg = P.decode_json(first, self.srv.limits.max_control_bytes)
            if msg["type"] != "hello":
                raise ProtocolError("bad_message",
                                    f"the first message must be a hello, got {msg['type']!r}")
            if "version" not in msg:  # a missing field, as for every message
                raise ProtocolError("bad_message", "missing field 'version' (the integer "
                                    f"{P.PROTOCOL_VERSION})")
            version = msg["version"]
            # The integer itself: 1.0 and true compare equal to 1 in Python, JSON tells them
            # apart, and a client that sends them speaks some other dialect.
            if type(version) is not int or version != P.PROTOCOL_VERSION:
                raise ProtocolError(
                    "bad_version",
                    f"protocol version {version!r} not supported; this server speaks "
                    f"{P.PROTOCOL_VERSION}",
                )
            re = P.request_id(msg)
            conn.name = P.field_str(msg, "name", "guest", max_len=32) or "guest"
            joins = hello_joins(msg)
        except ProtocolError as e:
            self.srv.stats["bad_messages"] += 1
            conn.error(e)
            return False
        conn.hello_done = True
        self.srv.lobby.shown()
        conn.send_json({
            "type": "welcome",
            "version": P.PROTOCOL_VERSION,
            "client": conn.id,
            "name": conn.name,
            "server_time": time.perf_counter() - self.srv.epoch,
            "scenes": sorted(self.srv.scenes),
            "rooms": self.srv.lobby.listing(),
            "re": re,
        })
        if joins:  # hello may carry a join: the same fields as a join message
            waiting = self._on_control(conn, {**msg, "type": "join"})
            if waiting is not None:
                await waiting
        return True

    def _on_text(self, conn: Conn, text: str) -> Awaitable[None] | None:
        if not conn.control_bucket.take():
            self.srv.stats["bad_messages"] += 1
            conn.error("rate_limited", f"at most {conn.control_bucket.rate:g} control "
                                       "messages a second; this one was dropped")
            if conn.rate_dropped():
                conn.drop("too many messages")
            return
        try:
            msg = P.decode_json(text, self.srv.limits.max_control_bytes)
        except ProtocolError as e:
            self.srv.stats["bad_messages"] += 1
            conn.error(e)
            return None
        return self._on_control(conn, msg)

    def _on_binary_now(self, conn: Conn, data: bytes) -> None:
        """A binary message handed over by ``Connection`` as it arrives: what the read loop
        of ``_handler`` does with one, which stops reading once the client is closed."""
        if conn.closed:
            return
        self.srv.stats["messages_in"] += 1
        conn.received += 1
        try:
            self._on_binary(conn, data)
        except Exception:  # pragma: no cover - a bug: like a failing handler, close 1011
            log.exception("handling a binary message from client %s failed", conn.id)
            conn.fail("internal error")

    def _on_binary(self, conn: Conn, data: bytes) -> None:
        if not conn.binary_bucket.take():
            self.srv.stats["bad_messages"] += 1
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
            self.srv.stats["bad_messages"] += 1
            conn.error(e)

    def _on_control(self, conn: Conn, msg: dict[str, Any]) -> Awaitable[None] | None:
        """Answers a control message; an awaitable when the answer waits for the shared
        directory (the caller awaits it before reading the client's next message)."""
        t = msg["type"]
        if t != "ping":  # a keep-alive is not activity (Limits.lobby_idle_s)
            conn.last_in = time.monotonic()
        handler = self.handlers.get(t)
        try:
            re = P.request_id(msg)  # a bad id is refused before anything is done
        except ProtocolError as e:
            self.srv.stats["bad_messages"] += 1
            conn.error(e)
            return None

        def call() -> Reply:
            if handler is None:
                raise ProtocolError("unknown_type", f"unknown message type {t!r}")
            return handler(conn, msg)

        return self._answer(conn, re, call)

    def _answer(self, conn: Conn, re: object, call: Callable[[], Reply]
                ) -> Awaitable[None] | None:
        try:
            reply = call()
            if isinstance(reply, Later):
                return self._answer_later(conn, re, reply.wait, reply.reply, fresh=False)
        except NotInView:  # a room made elsewhere since the last read: asked once it is read
            return self._answer_later(conn, re, self.srv.lobby.hooks.fresh_view(), call,
                                      fresh=True)
        except ProtocolError as e:
            self.srv.stats["bad_messages"] += 1
            conn.error(e, re=re)
            return None
        except Moved as m:  # the room lives elsewhere: the client sends this request there
            reply = {"type": "redirect", "url": self._as_seen_by(conn, m.url),
                     "reason": m.reason}
            if m.with_fields:
                reply["with"] = m.with_fields
        if reply is None and re is not None:
            reply = {"type": "ok"}
        if reply is not None:
            if re is not None:
                reply["re"] = re
            conn.send_json(reply)
        return None

    async def _answer_later(self, conn: Conn, re: object, wait: Awaitable[Any],
                            call: Callable[[], Reply], fresh: bool
                            ) -> None:
        try:
            async with asyncio.timeout(3 * IO_TIMEOUT_S):
                await wait
        except Exception:  # away or slow: answered from the view as it is
            pass
        if conn.closed:
            return
        if fresh:
            with self.srv.lobby.viewed_fresh():
                self._answer(conn, re, call)
        else:
            self._answer(conn, re, call)

    # --- control messages (the table in __init__ names them) -----------------------------
    def _msg_hello(self, conn: Conn, msg: dict[str, Any]) -> dict[str, Any]:
        raise ProtocolError("not_allowed", "hello was already received")

    def _msg_ping(self, conn: Conn, msg: dict[str, Any]) -> dict[str, Any]:
        t = P.field_float(msg, "t", None, -1e12, 1e12)
        return {"type": "pong", "t": t, "server_time": time.perf_counter() - self.srv.epoch}

    def _msg_list_rooms(self, conn: Conn, msg: dict[str, Any]) -> dict[str, Any]:
        self.srv.lobby.shown()
        return self.srv.lobby.rooms_message()

    def _msg_create_room(self, conn: Conn, msg: dict[str, Any]) -> dict[str, Any] | Later:
        name = P.field_str(msg, "name", "room", max_len=48) or "room"
        scene = P.field_str(msg, "scene", None, max_len=64)
        public = P.field_bool(msg, "public", True)
        settings = parse_settings(msg)
        cap = self.srv.limits.record_cap_max_s
        if settings.record_cap_s > cap:
            if "record_cap_s" in msg:
                raise ProtocolError("bad_message", f"record_cap_s {settings.record_cap_s:g} "
                                    f"is over this server's limit of {cap:g} s")
            settings.record_cap_s = cap
        self.srv.lobby.scene_name(scene)  # a bad request is refused here, not sent on
        # Moved: another process or host takes new rooms now (unless one sent it here). The
        # asking client is not counted: it leaves with the request.
        if not P.field_bool(msg, "placed", False):
            self.srv.lobby.place(len(self.srv.clients) - 1)
        mine = self.srv.lobby.rooms_of(conn.address)
        if mine >= self.srv.limits.rooms_per_address:
            raise ProtocolError("too_many_rooms", f"{conn.address} already has {mine} open rooms "
                                f"(limit {self.srv.limits.rooms_per_address}); close one first")
        room = self.srv.lobby.create(name, scene, public=public, settings=settings, owner=conn.id,
                                 address=conn.address)
        reply = {"type": "room_created", "room": room.id, "code": room.code, "state": room.info()}
        return reply if room.published is None else Later(room.published, lambda: reply)

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
        # A room id is only looked up, never stored: lobby.get names a bad one (as repr).
        room_id = msg.get("room")
        self._room_options(conn, msg)
        if token is not None:
            if room_id is None:  # the token names its room: Moved when it lives elsewhere
                room_id = token_room(token)
                try:
                    room = self.srv.lobby.get(room_id) if room_id is not None else None
                except ProtocolError:
                    raise ProtocolError("bad_token",
                                        "reconnect token unknown or expired") from None
            else:
                room = self.srv.lobby.get(room_id)
            rooms = [room] if room is not None else list(self.srv.lobby.rooms.values())
            for r in rooms:
                try:
                    return r.resume(conn, token)
                except ProtocolError:
                    continue
            raise ProtocolError("bad_token", "reconnect token unknown or expired")
        if room_id is None:
            raise ProtocolError("bad_message", "missing field 'room' (a room id from the "
                                "room list, or a 'token' to resume a seat)")
        room = self.srv.lobby.get(room_id)
        code = P.field_str(msg, "code", None, max_len=64)
        if room.sim.asleep:  # waking a room costs what a new one does
            why = self.srv.lobby.hooks.busy()
            if why is not None:
                raise ProtocolError("server_busy", why)
        if role == "player":
            seat = P.field_int(msg, "seat", None, -(2**31), 2**31)  # the room names bad seats
            return room.join_player(conn, seat, conn.name, code)
        if role == "spectator":
            room.check_code(code)  # a private room's size is its own business
            if len(room.spectators) >= self.srv.limits.spectators_per_room:
                raise ProtocolError("room_full", f"room {room.id} already has "
                                    f"{len(room.spectators)} spectators (the limit)")
            return room.join_spectator(conn, code)
        raise ProtocolError("bad_message", f"'role': must be 'player' or 'spectator', got "
                            f"{role!r}")

    def _as_seen_by(self, conn: Conn, url: str) -> str:
        """A sibling process's address as this client can reach it: processes of one
        machine publish the address they listen on (127.0.0.1 for a wildcard), so the
        client gets the host name it used itself, with the sibling's port."""
        mine = urllib.parse.urlsplit(getattr(self.srv, "own_url", "") or "")
        there = urllib.parse.urlsplit(url)
        req = getattr(conn.ws, "request", None)
        host = req.headers.get("Host") if req is not None else None
        if not host or there.hostname != mine.hostname or there.port is None:
            return url
        name = urllib.parse.urlsplit(f"//{host}").hostname or there.hostname
        name = f"[{name}]" if ":" in name else name
        return urllib.parse.urlunsplit((there.scheme, f"{name}:{there.port}", there.path, "",
                                        ""))

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
        seat = P.field_int(msg, "seat", None, -(2**31), 2**31)  # the room names bad seats
        difficulty = P.field_float(msg, "difficulty", room.settings.bot_difficulty, 0.0, 1.0)
        assert difficulty is not None
        room.add_bot(seat, difficulty)

    def _msg_remove_bot(self, conn: Conn, msg: dict[str, Any]) -> None:
        room = self._in_room(conn)
        if not room.may_control(conn):
            raise ProtocolError("not_allowed", "only the room's host can remove bots")
        seat = P.field_int(msg, "seat", None, -(2**31), 2**31, required=True)
        assert seat is not None
        room.remove_bot(seat)

    def _msg_state(self, conn: Conn, msg: dict[str, Any]) -> dict[str, Any]:
        return {"type": "room", **self._in_room(conn).info()}

