"""The gateway's relay: each client connection accepted on the public port gets a
connection of its own to the engine's Unix socket, opened by a PROXY line naming the
client (``server.shared.proxyline``), then the bytes both ways until either side ends.
The engine speaks the protocol (websocket and HTTP alike), so a client sees one server on
one port whichever gateway the kernel gave it to, and never a redirect inside the host.

While the engine cannot be reached (it is being restarted), a request is answered
``503`` with a JSON body saying so, and the client retries. When the engine vanishes under
a websocket client (its stream ends with no close frame, and the engine's socket no longer
answers), the gateway tells a client that was in a room that the room stopped, as the
engine does when a room's simulation fails (the event and the error ``room_stopped``),
then closes the client 1011 saying so (``frames``): the engine held the client's session,
so its connection cannot stay open in the lobby as after a room's own failure.

Once the engine's socket is connected, both sockets go to the gateway's pump
(``_native.Pump``, native/net/pump.hpp), one native thread that relays every connection's
bytes both ways (backpressure, half-closes passed on, a side that fails ending the other)
and serves the lanes (``server.shared.lanes``): a seated player's HIPs, its CORNERs and a
watcher's MESH never reach Python. Python keeps what is rare: accepting, the engine's
connection and PROXY line, the 503, parsing the engine's lane messages, and what to tell a
client whose engine's stream ended.

A client's socket has a fixed kernel send buffer, ``send_buffer`` (the host's
``Limits.socket_send_buffer``), as the engine's sockets have: not the megabytes TCP
autotuning would give one that stops reading. A websocket client that stays behind at the
pump (more than 64 KiB unsent to it, or unsent bytes and none taken) for longer than
``slow_drop_s`` (the host's ``Limits.slow_drop_s``) is dropped there, as the engine drops
one: its connection to the engine is closed (the engine sees it go, as any client's close
at its gateway), and it gets a close frame, 1008 ``too slow: ...``, after what is queued
for it (cut 2 s later if that has not gone out), or is cut where none can be written. A
gateway process is given both as ``--slow-drop-s`` and ``--send-buffer``."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import logging
import os
import socket
from collections.abc import Coroutine
from pathlib import Path
from typing import Any

from ... import _native
from ..shared import proxyline
from ..shared.lanes import ctl_path, parse_lane
from ..shared.listen import ACCEPT_BACKLOG
from .frames import close_frame, text_frame
from .lanes import EngineLink, pump_coalesce_s

CHUNK = 1 << 16  # bytes a client may send before its engine answers
HEAD_WAIT_S = 5.0  # for a request's head, before a 503 while the engine is away
RETRY_AFTER_S = 2  # told to a client while the engine is away
CONNECT_WAIT_S = HEAD_WAIT_S  # for a place in the engine's full accept backlog, then a 503
ENGINE_CHECK_S = 0.3  # an engine holds a new connection open this long, waiting for its line
ENGINE_GONE = "the host's engine stopped: its rooms are lost; reconnect in a few seconds"
ROOM_GONE = "the host's engine stopped"  # room_stopped's reason
SEND_BUFFER = 128 * 1024  # a client's SO_SNDBUF where none is given (Limits' default)

log = logging.getLogger("clothball.gateway")


async def connect_engine(path: str, wait_s: float) -> socket.socket:
    """A connected Unix socket to the engine at ``path``. While the engine's accept backlog
    is full, a non-blocking ``connect`` fails with ``EAGAIN``, and asyncio's own connect
    would take that socket for connected (it polls writable at once, with no error) and
    the first write fail: the client's connection would end with no answer (issue 43).
    Here it is tried again, at growing intervals, for up to ``wait_s``; then ``OSError``
    (the client is answered 503). Any other failure (no socket, refused: no engine)
    raises at once."""
    loop = asyncio.get_running_loop()
    end = loop.time() + wait_s
    pause = 0.002
    while True:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.setblocking(False)
        try:
            sock.connect(path)
            return sock
        except BlockingIOError:  # EAGAIN: the backlog is full
            sock.close()
            now = loop.time()
            if now >= end:
                raise OSError(errno.EAGAIN, "the engine's accept backlog stayed full") from None
            await asyncio.sleep(min(pause, end - now))
            pause = min(pause * 2, 0.05)
        except BaseException:
            sock.close()
            raise


class Gateway:
    """Relays the public port ``host:port`` to the engine socket ``engine``. ``link``: where
    its lanes' blocks and wake-up come from: the engine's control socket (a gateway
    process's ``EngineLink``, the default), or, for the engine's own port, the engine's
    ``server.lanes.local.LocalLink``; ``reuse_port``: the port is shared with other
    processes (a host's gateways); ``slow_drop_s``: how long a client may stay behind
    before the pump drops it (None: the pump's default, ``Limits.slow_drop_s``'s);
    ``send_buffer``: each client socket's ``SO_SNDBUF`` (None: ``SEND_BUFFER``)."""

    def __init__(self, host: str, port: int, engine: Path, *, link: Any = None,
                 reuse_port: bool = True, slow_drop_s: float | None = None,
                 send_buffer: int | None = None) -> None:
        self.host, self.port, self.engine = host, port, engine
        self.reuse_port = reuse_port
        self.send_buffer = SEND_BUFFER if send_buffer is None else send_buffer
        if self.send_buffer <= 0:
            raise ValueError(f"a client socket's send buffer: bytes > 0, got {send_buffer}")
        self.server: asyncio.Server | None = None
        given = {"coalesce_s": pump_coalesce_s(), "slow_drop_s": slow_drop_s}
        self.pump = _native.Pump(**{k: v for k, v in given.items() if v is not None})
        # Its clients' lanes served here (server.shared.lanes).
        if link is None:
            link = EngineLink(ctl_path(engine), self.pump)
        else:
            link.attach(self.pump)
        self.lanes = link
        self._open: set[asyncio.BaseTransport] = set()  # clients not yet handed to the pump
        self._tasks: set[asyncio.Task[None]] = set()

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        self.server = await loop.create_server(
            lambda: _Client(self), self.host, self.port, reuse_port=self.reuse_port,
            backlog=ACCEPT_BACKLOG)
        loop.add_reader(self.pump.event_fd, self._events)
        self.lanes.start()

    async def stop(self) -> None:
        """Stop accepting and cut every relayed connection (both sides)."""
        if self.server is not None:
            self.server.close()
        for transport in list(self._open):
            transport.abort()
        with contextlib.suppress(ValueError, OSError):
            asyncio.get_running_loop().remove_reader(self.pump.event_fd)
        self.pump.stop()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self.lanes.stop()

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _events(self) -> None:
        """What the pump tells: a lane message, an engine's stream that ended, a block
        to fetch, the frame wake-up to arm."""
        for ev in self.pump.take_events():
            kind, conn = ev[0], ev[1]
            if kind == "lane":
                self._lane(conn, ev[2])
            elif kind == "ended":
                self._spawn(self._ended(conn, ev[2], ev[3], ev[4], ev[5]))
            elif kind == "block":
                self.lanes.want_block(conn)
            elif kind == "arm":
                self.lanes.want_armed(ev[1])

    def _lane(self, conn: int, payload: bytes) -> None:
        """The engine opened (or closed) a client's lane."""
        try:
            spec = parse_lane(payload)
        except (ValueError, KeyError, TypeError) as e:
            log.warning("the engine sent a lane message that is not one (%s): %.80r", e, payload)
            spec = None
        if spec is None:
            self.pump.close_lane(conn)
            return
        # The room as the engine's compact JSON writes it: the pump matches it against
        # the stream's "joined" (game.wire.protocol.encode_json).
        self.pump.open_lane(conn, json.dumps(spec.room), spec.block, spec.slot,
                            -1 if spec.seat is None else spec.seat, spec.occupant,
                            spec.lo, spec.hi, spec.corner_interval, spec.binary_rate,
                            spec.binary_burst, -1 if spec.board is None else spec.board,
                            spec.board_slot)
        self.lanes.want_block(spec.block)

    async def _ended(self, conn: int, between: bool, room: str | None, frame: int,
                     time: float) -> None:
        """The engine's stream ended: when the engine itself is gone (its socket no longer
        answers), the room's room_stopped and a close frame of the gateway's own, then the
        end of file to the client."""
        tail = b""
        try:
            if between and not await self._engine_answers():
                if room is not None:
                    # docs/protocol.md's event and error (the gateway imports nothing of
                    # the game: the two messages are written here).
                    name = json.loads(room)
                    tail += text_frame(
                        {"type": "event", "event": "room_stopped", "room": name,
                         "frame": max(frame, 0), "time": time, "reason": ROOM_GONE})
                    tail += text_frame(
                        {"type": "error", "code": "room_stopped",
                         "message": f"room {name} stopped: {ROOM_GONE}"})
                tail += close_frame(1011, ENGINE_GONE)
        finally:
            self.pump.finish(conn, tail)

    async def _engine_answers(self) -> bool:
        """Whether the engine is there: its socket takes a connection and holds it open,
        waiting for the PROXY line (a dying engine's socket may still take a connection
        into its backlog, which is then reset)."""
        try:
            sock = await connect_engine(str(self.engine), ENGINE_CHECK_S)
            r, w = await asyncio.open_unix_connection(sock=sock)
        except OSError:
            return False
        try:
            await asyncio.wait_for(r.read(1), ENGINE_CHECK_S)
            return False  # closed on us: no engine waits for our line
        except TimeoutError:
            return True
        except OSError:
            return False
        finally:
            w.transport.abort()


class _Client(asyncio.Protocol):
    """A client's connection on the public port until its engine's connection is open
    (then both are the pump's)."""

    def __init__(self, gw: Gateway) -> None:
        self.gw = gw
        self.t: asyncio.Transport | None = None
        self.early: bytearray = bytearray()  # read before the engine answered
        self.head = asyncio.Event()  # a request's head is in ``early`` (or the client ended)
        self.eof = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.t = transport
        sock = transport.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.gw.send_buffer)
        self.gw._open.add(transport)
        self.gw._spawn(self._connect())

    async def _connect(self) -> None:
        try:
            sock = await connect_engine(str(self.gw.engine), CONNECT_WAIT_S)
        except OSError:
            await self._engine_away()
            return
        t = self.t
        assert t is not None
        if t.is_closing():  # the client went while the engine answered
            sock.close()
            return
        line = proxyline.encode(t.get_extra_info("peername"), t.get_extra_info("sockname"),
                                lanes=True)
        # The client's socket, duplicated for the pump: the transport's own is closed
        # with it (abort closes, never shuts down, so the connection stays open).
        t.pause_reading()
        client = os.dup(t.get_extra_info("socket").fileno())
        self.gw.pump.add(client, sock.detach(), line + bytes(self.early), self.eof)
        self.early = bytearray()
        t.abort()

    def data_received(self, data: bytes) -> None:
        self.early += data
        if b"\r\n\r\n" in self.early:
            self.head.set()
        if len(self.early) >= CHUNK:  # no engine yet: read no more until it answers
            assert self.t is not None
            self.t.pause_reading()

    def eof_received(self) -> bool:
        self.eof = True
        self.head.set()
        return True  # the engine's answer may still be on its way: keep writing

    def connection_lost(self, exc: Exception | None) -> None:
        self.head.set()
        if self.t is not None:
            self.gw._open.discard(self.t)

    async def _engine_away(self) -> None:
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self.head.wait(), HEAD_WAIT_S)
        body = json.dumps({"error": "the host's engine is restarting: try again in a few "
                                    "seconds", "status": 503}).encode()
        head = (f"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
                f"Content-Length: {len(body)}\r\nRetry-After: {RETRY_AFTER_S}\r\n"
                "Connection: close\r\n\r\n").encode()
        assert self.t is not None
        if not self.t.is_closing():
            self.t.write(head + body)
            self.t.close()


__all__ = ["Gateway"]
