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

The relay works on the transports themselves (``asyncio.Protocol``): each chunk read on
one side is written to the other from the read callback, with no stream buffer and no
task in between; a side whose write buffer is full pauses the other side's reading
(backpressure). An end of file is passed on (a half-close), and a side that fails aborts
the other."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import socket
from collections.abc import Coroutine
from pathlib import Path
from typing import Any

from ...game.wire.wsframe import FrameTap
from ..lanes.lane import Lane
from ..shared import proxyline
from ..shared.lanes import ctl_path, parse_lane
from ..shared.listen import ACCEPT_BACKLOG
from .frames import ServerFrames, close_frame, text_frame
from .lanes import WRITE_SKIP, SocketLinks, client_frames, lanes_wanted

CHUNK = 1 << 16  # bytes read at a time, each way
WRITE_HIGH = 1 << 18  # a side's buffered bytes above which its reader waits (backpressure)
HEAD_WAIT_S = 5.0  # for a request's head, before a 503 while the engine is away
RETRY_AFTER_S = 2  # told to a client while the engine is away
CONNECT_WAIT_S = HEAD_WAIT_S  # for a place in the engine's full accept backlog, then a 503
ENGINE_CHECK_S = 0.3  # an engine holds a new connection open this long, waiting for its line
ENGINE_GONE = "the host's engine stopped: its rooms are lost; reconnect in a few seconds"
ROOM_GONE = "the host's engine stopped"  # room_stopped's reason


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
    """Relays the public port ``host:port`` to the engine socket ``engine``."""

    def __init__(self, host: str, port: int, engine: Path) -> None:
        self.host, self.port, self.engine = host, port, engine
        self.server: asyncio.Server | None = None
        # Its clients' lanes served here (server.lanes), unless off.
        self.lanes = SocketLinks(ctl_path(engine)) if lanes_wanted() else None
        self._open: set[asyncio.BaseTransport] = set()  # both sides of every relay
        self._tasks: set[asyncio.Task[None]] = set()

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        self.server = await loop.create_server(
            lambda: _Client(self), self.host, self.port, reuse_port=True,
            backlog=ACCEPT_BACKLOG)
        if self.lanes is not None:
            self.lanes.start()

    async def stop(self) -> None:
        """Stop accepting and cut every relayed connection (both sides)."""
        if self.server is not None:
            self.server.close()
        for transport in list(self._open):
            transport.abort()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self.lanes is not None:
            await self.lanes.stop()

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

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
    """A client's connection on the public port, and its relay to the engine."""

    def __init__(self, gw: Gateway) -> None:
        self.gw = gw
        self.t: asyncio.Transport | None = None
        self.engine: _Engine | None = None
        self.early: bytearray | None = bytearray()  # read before the engine answered
        self.head = asyncio.Event()  # a request's head is in ``early`` (or the client ended)
        self.eof = False
        self.frames: FrameTap | None = None  # its websocket frames, once upgraded
        self.lane: Lane | None = None  # its open lane (server.lanes)
        # lane messages waiting for a message boundary (header, payload), the newest of each
        self.pending: dict[str, tuple[bytes, bytes]] = {}

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.t = transport
        sock = transport.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        transport.set_write_buffer_limits(high=WRITE_HIGH)
        self.gw._open.add(transport)
        self.gw._spawn(self._connect())

    async def _connect(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            sock = await connect_engine(str(self.gw.engine), CONNECT_WAIT_S)
            _, engine = await loop.create_unix_connection(lambda: _Engine(self), sock=sock)
        except OSError:
            await self._engine_away()
            return
        assert self.t is not None and engine.t is not None
        if self.t.is_closing():  # the client went while the engine answered
            engine.t.abort()
            return
        self.engine = engine
        early, self.early = self.early or b"", None
        engine.t.write(proxyline.encode(self.t.get_extra_info("peername"),
                                        self.t.get_extra_info("sockname"),
                                        lanes=self.gw.lanes is not None) + early)
        if self.eof and engine.t.can_write_eof():
            engine.t.write_eof()
        self.t.resume_reading()

    def data_received(self, data: bytes) -> None:
        if self.engine is not None:
            assert self.engine.t is not None
            if self.frames is None and self.gw.lanes is not None and self.engine.frames.websocket:
                self.frames = client_frames(self._take)  # the handshake is done: frames follow
            if self.frames is not None:
                data = self.frames.feed(data)
            if data:
                self.engine.t.write(data)
        elif self.early is not None:
            self.early += data
            if b"\r\n\r\n" in self.early:
                self.head.set()
            if len(self.early) >= CHUNK:  # no engine yet: read no more until it answers
                assert self.t is not None
                self.t.pause_reading()

    # --- its lane ---------------------------------------------------------------------------
    def _take(self, payload: bytes) -> bool:
        return self.lane is not None and self.lane.take(payload)

    def on_lane(self, payload: bytes) -> None:
        """The engine opened (or closed) this client's lane."""
        if self.lane is not None:
            self.lane.close()
            self.lane = None
        spec = parse_lane(payload)
        if spec is not None and self.gw.lanes is not None and self.engine is not None:
            frames = self.engine.frames
            self.lane = Lane(spec, self.gw.lanes, self.write_lane, lambda: frames.room)

    def write_lane(self, kind: str, head: bytes, payload: bytes) -> None:
        """A message of the client's lane (a CORNER, a MESH) to the client, between two of
        the engine's messages (else the newest of each kind is held until the engine's
        stream is between two), unless the client is behind on reading. The engine's
        stream follower learns its room's frame from it, as from the engine's own."""
        t = self.t
        if t is None or t.is_closing() or t.get_write_buffer_size() > WRITE_SKIP:
            return
        engine = self.engine
        if engine is not None and engine.frames.between_messages():
            t.write(head + payload)
            engine.frames.sent_binary(payload)
            assert self.gw.lanes is not None
            self.gw.lanes.counts["messages_out"] += 1
        else:
            self.pending[kind] = (head, payload)

    def flush_pending(self) -> None:
        held, self.pending = self.pending, {}
        for kind, (head, payload) in held.items():
            self.write_lane(kind, head, payload)

    def eof_received(self) -> bool:
        self.eof = True
        self.head.set()
        if self.engine is not None:
            assert self.engine.t is not None
            if self.engine.t.can_write_eof():
                self.engine.t.write_eof()
        self.close_if_done()
        return True  # the engine's answer may still be on its way: keep writing

    def close_if_done(self) -> None:
        """Both ways have ended (the client's end of file, the engine's passed on): close
        the connection (and with it the engine's side, ``connection_lost``)."""
        if self.eof and self.engine is not None and self.engine.done and self.t is not None:
            self.t.close()

    def connection_lost(self, exc: Exception | None) -> None:
        self.head.set()
        if self.lane is not None:
            self.lane.close()
            self.lane = None
        if self.t is not None:
            self.gw._open.discard(self.t)
        if self.engine is not None and self.engine.t is not None:
            # One side failed (or both ended): end the other too.
            if exc is None:
                self.engine.t.close()
            else:
                self.engine.t.abort()

    def pause_writing(self) -> None:  # the client reads slowly: stop reading the engine
        if self.engine is not None and self.engine.t is not None:
            self.engine.t.pause_reading()

    def resume_writing(self) -> None:
        if self.engine is not None and self.engine.t is not None:
            self.engine.t.resume_reading()

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


class _Engine(asyncio.Protocol):
    """The engine's side of one relay: its bytes to the client, followed (``ServerFrames``)
    so that a client whose engine vanished is told its room stopped and gets a close frame
    that says so."""

    def __init__(self, client: _Client) -> None:
        self.client = client
        self.t: asyncio.Transport | None = None
        self.frames = ServerFrames(on_lane=client.on_lane)
        self.ended = False  # the engine's stream ended
        self.done = False  # and what follows it was written to the client

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.t = transport
        transport.set_write_buffer_limits(high=WRITE_HIGH)
        self.client.gw._open.add(transport)

    def data_received(self, data: bytes) -> None:
        data = self.frames.feed(data)  # lane messages taken out
        ct = self.client.t
        if ct is not None and not ct.is_closing():
            if data:
                ct.write(data)
            if self.client.pending and self.frames.between_messages():
                self.client.flush_pending()

    def eof_received(self) -> bool:
        self._end()
        return True  # the client's last bytes may still be on their way: keep writing

    def connection_lost(self, exc: Exception | None) -> None:
        if self.t is not None:
            self.client.gw._open.discard(self.t)
        self._end()

    def pause_writing(self) -> None:  # the engine reads slowly: stop reading the client
        if self.client.t is not None:
            self.client.t.pause_reading()

    def resume_writing(self) -> None:
        if self.client.t is not None:
            self.client.t.resume_reading()

    def _end(self) -> None:
        if not self.ended:
            self.ended = True
            self.client.gw._spawn(self._ended())

    async def _ended(self) -> None:
        """The engine's stream ended: when the engine itself is gone (its socket no longer
        answers), the room's room_stopped and a close frame of the gateway's own, then the
        end of file to the client."""
        try:
            await self._tell_client()
        finally:
            self.done = True
            self.client.close_if_done()

    async def _tell_client(self) -> None:
        ct, frames = self.client.t, self.frames
        if ct is None or ct.is_closing():
            return
        if frames.between_messages() and not await self.client.gw._engine_answers():
            if ct.is_closing():
                return
            if frames.room is not None:
                # docs/protocol.md's event and error (the gateway imports nothing of the
                # game: the two messages are written here).
                ct.write(text_frame(
                    {"type": "event", "event": "room_stopped", "room": frames.room,
                     "frame": max(frames.frame, 0), "time": frames.time, "reason": ROOM_GONE}))
                ct.write(text_frame(
                    {"type": "error", "code": "room_stopped",
                     "message": f"room {frames.room} stopped: {ROOM_GONE}"}))
            ct.write(close_frame(1011, ENGINE_GONE))
        if not ct.is_closing() and ct.can_write_eof():
            with contextlib.suppress(OSError):  # the client has gone meanwhile
                ct.write_eof()


__all__ = ["Gateway"]
