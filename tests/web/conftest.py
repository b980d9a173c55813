"""Helpers for the browser tests and the page's bench and screenshot scripts: a real game
server on a thread of its own and Debian's Chromium driven by Selenium through Debian's
chromedriver.

Nothing is downloaded: the driver is ``/usr/bin/chromedriver`` (or ``chromedriver`` on the
PATH) and Selenium Manager is never asked for one. WebGL2 runs on SwiftShader (software),
so no GPU or display is needed.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from clothball.game.sim.scene import Scene
from clothball.server.room import RoomSettings
from clothball.server.thread import ServerThread

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


@pytest.fixture(scope="module")
def driver() -> Iterator[Any]:
    """A headless Chromium of 1100 x 720 for a test module's pages (``make_driver``)."""
    d = make_driver(1100, 720)
    try:
        yield d
    finally:
        quit_driver(d)


def quit_driver(d: Any) -> None:
    """Quit the browser. Chromedriver waits on a frozen page (a test that found one) before
    it quits, minutes on end: a browser that does not answer a script is killed instead."""
    d.command_executor.client_config.timeout = 15
    try:
        d.execute_script("return 1")
    except Exception:  # noqa: BLE001 - frozen or gone: either way, no waiting on it
        _kill_children(d.service.process.pid)
    try:
        d.quit()
    except Exception:  # noqa: BLE001 - the session died with its browser
        d.service.stop()


def _kill_children(pid: int) -> None:
    """SIGKILL every process below ``pid`` (Linux /proc), deepest first."""
    parents: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        parents.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    order: list[int] = []
    todo = list(parents.get(pid, []))
    while todo:
        p = todo.pop()
        order.append(p)
        todo.extend(parents.get(p, []))
    for p in reversed(order):
        with contextlib.suppress(OSError):
            os.kill(p, signal.SIGKILL)


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


def web_server(data_dir: Path, *, scene: Scene | None = None, bots: int = 4,
               settings: RoomSettings | None = None, port: int = 0,
               **kw: Any) -> ServerThread:
    """A server for the page (not started): room ``main`` on ``scene`` (default classic),
    CPU backend, ``bots`` bots."""
    scene = scene or Scene.load("classic")
    return ServerThread(data_dir, scenes={scene.name: scene}, backend="cpu", bots=bots,
                        room_settings=settings or RoomSettings(autoplay=True), port=port, **kw)
