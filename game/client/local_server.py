"""An in-process game server on its own thread (``clothball play --local``)."""

from __future__ import annotations

import asyncio
import logging
import sys
import threading
from pathlib import Path
from typing import Any

log = logging.getLogger("clothball.client")


class LocalServer:
    """``server.app.GameServer`` on loopback (a free port) with ``bots`` bots in its main
    room, run by an asyncio loop on a daemon thread. ``start()`` returns the ws URL.
    ``scene``: a scene name, a TOML path or a ``game.scene.Scene``."""

    def __init__(self, data_dir: Path | str, *, bots: int = 3, scene: Any = "classic",
                 backend: str = "auto", first_to: int = 5, port: int = 0,
                 settings: dict[str, Any] | None = None) -> None:
        self.data_dir = Path(data_dir)
        self.bots = bots
        self.scene = scene
        self.backend = backend
        self.first_to = first_to
        self.port = port
        self.settings = settings or {}
        self.server: Any = None
        self.url = ""
        self.loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._stop: asyncio.Event | None = None
        self._error: BaseException | None = None

    def start(self, timeout: float = 60.0) -> str:
        self._thread = threading.Thread(target=self._run, name="clothball-local-server",
                                        daemon=True)
        self._thread.start()
        if not self._started.wait(timeout):
            raise TimeoutError("the local server did not start")
        if self._error is not None:
            raise RuntimeError(f"the local server did not start: {self._error}") from self._error
        return self.url

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as e:  # noqa: BLE001 - reported to start()
            self._error = e
            self._started.set()

    async def _main(self) -> None:
        from ...server.app import GameServer
        from ...server.room import RoomSettings
        from ..scene import Scene

        # The room thread needs the GIL briefly every frame (see server.host).
        sys.setswitchinterval(0.0005)
        self.loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        scene = self.scene if isinstance(self.scene, Scene) else Scene.load(self.scene)
        settings = RoomSettings(first_to=self.first_to, autoplay=True, **self.settings)
        self.server = GameServer(self.data_dir, scenes={scene.name: scene},
                                 backend=self.backend, host="127.0.0.1", port=self.port,
                                 bots=self.bots, room_settings=settings)
        await self.server.start()
        self.url = self.server.ws_url
        self._started.set()
        try:
            await self._stop.wait()
        finally:
            await self.server.stop()

    def stop(self, timeout: float = 10.0) -> None:
        if self.loop is not None and self._stop is not None and not self.loop.is_closed():
            try:
                self.loop.call_soon_threadsafe(self._stop.set)
            except RuntimeError:
                pass
        if self._thread is not None:
            self._thread.join(timeout)
