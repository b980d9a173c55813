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
so its connection cannot stay open in the lobby as after a room's own failure."""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
from pathlib import Path

from ..shared import proxyline
from .frames import ServerFrames, close_frame, text_frame

CHUNK = 1 << 16  # bytes read at a time, each way
WRITE_HIGH = 1 << 18  # a side's buffered bytes above which its reader waits (backpressure)
HEAD_WAIT_S = 5.0  # for a request's head, before a 503 while the engine is away
RETRY_AFTER_S = 2  # told to a client while the engine is away
ENGINE_CHECK_S = 0.3  # an engine holds a new connection open this long, waiting for its line
ENGINE_GONE = "the host's engine stopped: its rooms are lost; reconnect in a few seconds"
ROOM_GONE = "the host's engine stopped"  # room_stopped's reason


class Gateway:
    """Relays the public port ``host:port`` to the engine socket ``engine``."""

    def __init__(self, host: str, port: int, engine: Path) -> None:
        self.host, self.port, self.engine = host, port, engine
        self.server: asyncio.Server | None = None
        self._open: set[asyncio.BaseTransport] = set()  # both sides of every relay
        self._tasks: set[asyncio.Task[None]] = set()

    async def start(self) -> None:
        self.server = await asyncio.start_server(
            self._client, self.host, self.port, reuse_port=True, limit=CHUNK,
            backlog=1024)

    async def stop(self) -> None:
        """Stop accepting and cut every relayed connection (both sides)."""
        if self.server is not None:
            self.server.close()
        for transport in list(self._open):
            transport.abort()
        await asyncio.gather(*self._tasks, return_exceptions=True)

    async def _client(self, creader: asyncio.StreamReader, cwriter: asyncio.StreamWriter
                      ) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        self._open.add(cwriter.transport)
        try:
            await self._relay(creader, cwriter)
        except (ConnectionError, OSError, asyncio.IncompleteReadError):
            pass
        finally:
            self._open.discard(cwriter.transport)
            self._tasks.discard(task)
            cwriter.close()

    async def _relay(self, creader: asyncio.StreamReader, cwriter: asyncio.StreamWriter
                     ) -> None:
        sock = cwriter.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            ereader, ewriter = await asyncio.open_unix_connection(str(self.engine),
                                                                  limit=CHUNK)
        except OSError:
            await self._engine_away(creader, cwriter)
            return
        self._open.add(ewriter.transport)
        try:
            for w in (cwriter, ewriter):
                w.transport.set_write_buffer_limits(high=WRITE_HIGH)
            ewriter.write(proxyline.encode(cwriter.get_extra_info("peername"),
                                           cwriter.get_extra_info("sockname")))
            # Both ways at once; one side's end of file is passed on, and the relay ends
            # when both have ended (or either fails).
            await asyncio.gather(_pump(creader, ewriter), self._down(ereader, cwriter),
                                 return_exceptions=True)
        finally:
            self._open.discard(ewriter.transport)
            ewriter.close()

    async def _down(self, ereader: asyncio.StreamReader, cwriter: asyncio.StreamWriter
                    ) -> None:
        """The engine's bytes to the client, followed (``ServerFrames``) so that a client
        whose engine vanished gets a close frame that says so."""
        frames = ServerFrames()
        try:
            while data := await ereader.read(CHUNK):
                frames.feed(data)
                cwriter.write(data)
                await cwriter.drain()
        except (ConnectionError, OSError):
            pass
        if frames.between_messages() and not await self._engine_answers():
            if frames.room is not None:
                # docs/protocol.md's event and error (the gateway imports nothing of the
                # game: the two messages are written here).
                cwriter.write(text_frame(
                    {"type": "event", "event": "room_stopped", "room": frames.room,
                     "frame": max(frames.frame, 0), "time": frames.time, "reason": ROOM_GONE}))
                cwriter.write(text_frame(
                    {"type": "error", "code": "room_stopped",
                     "message": f"room {frames.room} stopped: {ROOM_GONE}"}))
            cwriter.write(close_frame(1011, ENGINE_GONE))
        with contextlib.suppress(ConnectionError, OSError):
            await cwriter.drain()
            if cwriter.can_write_eof():
                cwriter.write_eof()

    async def _engine_answers(self) -> bool:
        """Whether the engine is there: its socket takes a connection and holds it open,
        waiting for the PROXY line (a dying engine's socket may still take a connection
        into its backlog, which is then reset)."""
        try:
            r, w = await asyncio.open_unix_connection(str(self.engine))
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

    async def _engine_away(self, creader: asyncio.StreamReader,
                           cwriter: asyncio.StreamWriter) -> None:
        with contextlib.suppress(asyncio.TimeoutError, asyncio.LimitOverrunError,
                                 asyncio.IncompleteReadError, ValueError):
            await asyncio.wait_for(creader.readuntil(b"\r\n\r\n"), HEAD_WAIT_S)
        body = json.dumps({"error": "the host's engine is restarting: try again in a few "
                                    "seconds", "status": 503}).encode()
        head = (f"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
                f"Content-Length: {len(body)}\r\nRetry-After: {RETRY_AFTER_S}\r\n"
                "Connection: close\r\n\r\n").encode()
        cwriter.write(head + body)
        with contextlib.suppress(ConnectionError, OSError):
            await cwriter.drain()


async def _pump(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    try:
        while data := await reader.read(CHUNK):
            writer.write(data)
            await writer.drain()
        if writer.can_write_eof():
            writer.write_eof()
    except (ConnectionError, OSError):
        # One side is gone: end the other too (its own pump then reads end of file).
        writer.transport.abort()
        raise


__all__ = ["Gateway"]
