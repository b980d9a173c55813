"""Helpers for the browser tests and tools: a real game server in a background thread and
Debian's Chromium driven by Selenium through Debian's chromedriver.

Nothing is downloaded: the driver is ``/usr/bin/chromedriver`` (or ``chromedriver`` on the
PATH) and Selenium Manager is never asked for one. WebGL2 runs on SwiftShader (software),
so no GPU or display is needed.
"""

from __future__ import annotations

import asyncio
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from clothball.game.scene import Scene
from clothball.server.app import GameServer
from clothball.server.room import RoomSettings

CHROMIUM_CANDIDATES = ("/usr/bin/chromium", "/usr/bin/chromium-browser")
DRIVER_CANDIDATES = ("/usr/bin/chromedriver",)


def find_browser() -> tuple[str | None, str | None, str]:
    """(chromium, chromedriver, why-not) for this machine."""
    browser = next((p for p in CHROMIUM_CANDIDATES if Path(p).exists()), None) or shutil.which(
        "chromium"
    )
    driver = next((p for p in DRIVER_CANDIDATES if Path(p).exists()), None) or shutil.which(
        "chromedriver"
    )
    why = ""
    if browser is None:
        why = "chromium is not installed (apt-get install chromium chromium-driver)"
    elif driver is None:
        why = "chromedriver is not installed (apt-get install chromium-driver)"
    return browser, driver, why


def make_driver(width: int = 1280, height: int = 800, *, mobile: bool = False) -> Any:
    """A headless Chromium with WebGL2 (SwiftShader) and the console log captured."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    browser, driver, why = find_browser()
    if why:
        raise RuntimeError(why)
    opts = webdriver.ChromeOptions()
    opts.binary_location = browser
    for arg in (
        "--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-gl=angle",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
        "--disable-extensions", "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--mute-audio",
        "--disable-renderer-backgrounding", "--disable-background-timer-throttling",
        f"--window-size={width},{height}", "--force-device-scale-factor=1",
    ):
        opts.add_argument(arg)
    if mobile:
        opts.add_experimental_option("mobileEmulation", {
            "deviceMetrics": {"width": width, "height": height, "pixelRatio": 1.0, "touch": True},
        })
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    drv = webdriver.Chrome(service=Service(driver), options=opts)
    drv.set_script_timeout(60)
    return drv


def console_errors(driver: Any) -> list[dict[str, Any]]:
    """Console messages at error level since the last call (the log is drained)."""
    return [e for e in driver.get_log("browser") if e.get("level") == "SEVERE"]


def wait_for(pred: Callable[[], Any], timeout: float = 20.0, what: str = "",
             poll: float = 0.1) -> Any:
    end = time.monotonic() + timeout
    last: Any = None
    while time.monotonic() < end:
        try:
            last = pred()
        except Exception as e:  # noqa: BLE001 - the page may be between states
            last = e
        if last and not isinstance(last, Exception):
            return last
        time.sleep(poll)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what or pred} "
                         f"(last: {last!r})")


class ServerThread:
    """A GameServer on loopback (port 0 unless given) with its own event loop thread."""

    def __init__(self, data_dir: Path, *, scene: Scene | None = None, bots: int = 4,
                 settings: RoomSettings | None = None, port: int = 0,
                 **kw: Any) -> None:
        self.data_dir = Path(data_dir)
        self.scene = scene or Scene.load("classic")
        self.bots = bots
        self.settings = settings or RoomSettings(autoplay=True)
        self.port = port
        self.kw = kw
        self.loop: asyncio.AbstractEventLoop | None = None
        self.server: GameServer | None = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._stop: asyncio.Event | None = None
        self._error: BaseException | None = None

    def start(self) -> ServerThread:
        self._thread = threading.Thread(target=self._run, name="clothball-server", daemon=True)
        self._thread.start()
        if not self._started.wait(60):
            raise RuntimeError("the server did not start within 60 s")
        if self._error is not None:
            raise RuntimeError(f"the server failed to start: {self._error!r}")
        return self

    def _run(self) -> None:
        async def main() -> None:
            self.loop = asyncio.get_running_loop()
            self._stop = asyncio.Event()
            try:
                srv = GameServer(self.data_dir, scenes={self.scene.name: self.scene},
                                 backend="cpu", host="127.0.0.1", port=self.port,
                                 bots=self.bots, room_settings=self.settings, **self.kw)
                await srv.start()
            except BaseException as e:
                self._error = e
                self._started.set()
                raise
            self.server = srv
            self.port = srv.port
            self._started.set()
            try:
                await self._stop.wait()
            finally:
                await srv.stop()

        try:
            asyncio.run(main())
        except BaseException as e:  # noqa: BLE001 - reported by start()
            if self._error is None:
                self._error = e

    @property
    def url(self) -> str:
        assert self.server is not None
        return self.server.http_url

    def call(self, fn: Callable[[GameServer], Any], timeout: float = 10.0) -> Any:
        """Run fn(server) on the server's loop and return its result."""
        assert self.loop is not None and self.server is not None
        srv = self.server

        async def go() -> Any:
            return fn(srv)

        return asyncio.run_coroutine_threadsafe(go(), self.loop).result(timeout)

    def stop(self) -> None:
        if self.loop is not None and self._stop is not None and self._thread is not None:
            self.loop.call_soon_threadsafe(self._stop.set)
            self._thread.join(30)

    def __enter__(self) -> ServerThread:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
