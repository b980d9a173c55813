"""Server test helpers: a real game server on its own thread and event loop, for tests
that drive it from plain (blocking) code: hypothesis examples, raw sockets. Errors the
server logs are collected, so a test can assert that no exception escaped a connection
handler."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from clothball.server.app import GameServer
from clothball.server.room import RoomSettings

from tests.conftest import TINY


class ErrorLog(logging.Handler):
    """Keeps every ERROR (or worse) record: handler crashes, failed saves, stopped rooms."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)

    def texts(self) -> list[str]:
        return [f"{r.name}: {r.getMessage()} {r.exc_text or ''}" for r in self.records]


class LiveServer:
    def __init__(self, srv: GameServer, loop: asyncio.AbstractEventLoop, errors: ErrorLog
                 ) -> None:
        self.srv, self.loop, self.errors = srv, loop, errors

    def call(self, fn: Any, *args: Any) -> Any:
        """Run ``fn(*args)`` on the server's loop (its state is not thread-safe) and wait."""
        async def go() -> Any:
            return fn(*args)

        return asyncio.run_coroutine_threadsafe(go(), self.loop).result(10)

    def http(self, raw: bytes, timeout: float = 5.0) -> bytes:
        """Send raw bytes to the HTTP port; the whole answer (until the server closes)."""
        with socket.create_connection(("127.0.0.1", self.srv.port), timeout=timeout) as s:
            s.sendall(raw)
            chunks = []
            while True:
                try:
                    b = s.recv(65536)
                except (TimeoutError, ConnectionResetError):
                    break
                if not b:
                    break
                chunks.append(b)
            return b"".join(chunks)


@contextlib.contextmanager
def live_server(data: Path, **kw: Any) -> Iterator[LiveServer]:
    errors = ErrorLog()
    # The server's loggers only: a test's own clients log under websockets.client.
    loggers = [logging.getLogger("clothball"), logging.getLogger("websockets.server")]
    for lg in loggers:
        lg.addHandler(errors)
    loop = asyncio.new_event_loop()
    kw.setdefault("room_settings", RoomSettings(bots_allowed=False))
    srv = GameServer(data, scenes={"tiny": TINY}, backend="cpu", host="127.0.0.1", port=0, **kw)
    started = threading.Event()

    def run() -> None:
        asyncio.set_event_loop(loop)
        loop.run_until_complete(srv.start())
        started.set()
        loop.run_forever()
        loop.run_until_complete(srv.stop())
        loop.close()

    t = threading.Thread(target=run, name="live-server", daemon=True)
    t.start()
    if not started.wait(30):
        raise RuntimeError("the live server did not start")
    try:
        yield LiveServer(srv, loop, errors)
    finally:
        loop.call_soon_threadsafe(loop.stop)
        t.join(30)
        for lg in loggers:
            lg.removeHandler(errors)
