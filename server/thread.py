"""A game server on a thread of its own, for callers that are not async: ``clothball play
--local``, the tests and the tools. The one helper for that; the server itself is
``server.app.GameServer``, run by an asyncio loop on a daemon thread."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .app import GameServer, ServerConfig


class ServerThread:
    """``GameServer(ServerConfig(data_dir, **kw))`` (loopback and a free port unless ``kw``
    says otherwise; ``directory`` and ``bot_factory`` go to the server) on its own event
    loop thread. ``start()`` returns once it listens; use it as
    a context manager to stop it on the way out."""

    def __init__(self, data_dir: Path | str, **kw: Any) -> None:
        kw.setdefault("host", "127.0.0.1")
        kw.setdefault("port", 0)
        self.data_dir = Path(data_dir)
        self.kw = kw
        self.loop: asyncio.AbstractEventLoop | None = None
        self.server: GameServer | None = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None

    def start(self, timeout: float = 60.0) -> ServerThread:
        if self._thread is not None:
            raise RuntimeError("this ServerThread was started already")
        self._thread = threading.Thread(target=self._run, name="clothball-server", daemon=True)
        self._thread.start()
        if not self._started.wait(timeout):
            raise RuntimeError(f"the server did not start within {timeout:g} s")
        if self._error is not None:
            raise RuntimeError(f"the server did not start: {self._error}") from self._error
        return self

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        asyncio.set_event_loop(loop)
        self.loop = loop
        kw = dict(self.kw)
        collaborators = {k: kw.pop(k) for k in ("directory", "bot_factory") if k in kw}
        srv = GameServer(ServerConfig(self.data_dir, **kw), **collaborators)
        try:
            loop.run_until_complete(srv.start())
        except BaseException as e:  # noqa: BLE001 - reported by start()
            self._error = e
            self._started.set()
            loop.close()
            return
        self.server = srv
        self._started.set()
        try:
            loop.run_forever()  # until stop()
        finally:
            loop.run_until_complete(srv.stop())
            loop.close()

    @property
    def port(self) -> int:
        assert self.server is not None, "not started"
        return self.server.port

    @property
    def url(self) -> str:
        """The HTTP address (spectator page, API)."""
        assert self.server is not None, "not started"
        return self.server.http_url

    @property
    def ws_url(self) -> str:
        assert self.server is not None, "not started"
        return self.server.ws_url

    def call(self, fn: Callable[[GameServer], Any], timeout: float = 10.0) -> Any:
        """Run ``fn(server)`` on the server's loop (its state is not thread-safe) and return
        its result."""
        assert self.loop is not None and self.server is not None, "not started"
        srv = self.server

        async def go() -> Any:
            return fn(srv)

        return asyncio.run_coroutine_threadsafe(go(), self.loop).result(timeout)

    def stop(self, timeout: float = 30.0) -> None:
        """Stop the server (its rooms, connections and the writes under way) and the
        thread."""
        if self.loop is not None and self.server is not None and not self.loop.is_closed():
            try:
                self.loop.call_soon_threadsafe(self.loop.stop)
            except RuntimeError:  # the loop closed meanwhile
                pass
        if self._thread is not None:
            self._thread.join(timeout)

    def __enter__(self) -> ServerThread:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
