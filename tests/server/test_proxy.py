"""``clothball host`` behind a real nginx (issue 33, item 5): the proxy's own process,
started and stopped here on free ports with its own files in a temporary directory, and
the configuration ``docs/cluster.md`` gives in its "Deployment" section (read from there:
one copy). Everything goes through the proxy's one port: the page in Chromium spectates and
replays, players join ``main`` and a created room and play, and the server tells clients
apart by the ``X-Forwarded-For`` its trusted proxy writes.

Skips, saying why, where nginx is not installed (``apt-get install nginx``; CI installs it);
the page's test also where Chromium is not.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import shutil
import subprocess
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import websockets
from clothball.game.net.client import NetClient
from clothball.game.sim.scene import ASSETS, Scene
from clothball.server.hostproc import free_port, start_host, stop_host, wait_port
from clothball.server.room import RoomSettings

from tests.server.conftest import run
from tests.web.conftest import find_browser, make_driver, quit_driver, wait_for, web_server

ROOT = Path(__file__).resolve().parents[2]
NGINX = next((p for p in ("/usr/sbin/nginx",) if Path(p).exists()), None) or \
    shutil.which("nginx")
pytestmark = pytest.mark.skipif(NGINX is None, reason="nginx is not installed (apt-get "
                                "install nginx): the reverse-proxy tests need it")
_, _, NO_BROWSER = find_browser()

# 1: one process; 2: an engine and a gateway on the one port (no join is redirected).
WORKERS = [1, 2]

# Fast rounds for the recorded round the page replays (as tests/web/test_web_browser.py).
FAST = RoomSettings(autoplay=True, first_to=3, countdown=0.6, reset_speed=1.5,
                    restart_delay=1.0)
PER_ADDRESS = 3  # --limit conns_per_address: what X-Forwarded-For is checked against


def deployment_config() -> str:
    """The nginx configuration of docs/cluster.md's "Deployment" section."""
    doc = (ROOT / "docs" / "cluster.md").read_text()
    section = doc.split("\n## Deployment", 1)[1].split("\n## ", 1)[0]
    m = re.search(r"```nginx\n(.*?)```", section, re.S)
    assert m is not None, "docs/cluster.md's Deployment section has no ```nginx block"
    return m.group(1)


def nginx_conf(tmp: Path, listen: int, upstream: int) -> Path:
    """A whole nginx.conf around the documented ``http`` part: its own pid file, logs and
    temporary files in ``tmp``, in the foreground, the documented ports replaced."""
    part = deployment_config()
    assert "listen 80;" in part and "127.0.0.1:8765" in part
    part = part.replace("listen 80;", f"listen 127.0.0.1:{listen};")
    part = part.replace("127.0.0.1:8765", f"127.0.0.1:{upstream}")
    (tmp / "clothball.conf").write_text(part)
    temps = "\n".join(f"    {k}_temp_path {tmp / k};"
                      for k in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"))
    conf = tmp / "nginx.conf"
    conf.write_text(f"""daemon off;
{"user root;  # its workers use this directory (root's, mode 0700)" if os.geteuid() == 0 else ""}
worker_processes 1;
pid {tmp / "nginx.pid"};
error_log {tmp / "error.log"} info;
events {{ worker_connections 256; }}
http {{
    access_log {tmp / "access.log"};
{temps}
    include {tmp / "clothball.conf"};
}}
""")
    return conf


@contextlib.contextmanager
def nginx(tmp: Path, upstream: int) -> Iterator[int]:
    """nginx in front of 127.0.0.1:``upstream``, on a free port (yielded)."""
    assert NGINX is not None
    tmp.mkdir(parents=True, exist_ok=True)
    port = free_port()
    conf = nginx_conf(tmp, port, upstream)
    cmd = [NGINX, "-p", str(tmp), "-c", str(conf), "-e", str(tmp / "error.log")]
    check = subprocess.run([*cmd, "-t"], capture_output=True, text=True)
    assert check.returncode == 0, check.stderr
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_port(port, "nginx")
        yield port
    finally:
        proc.terminate()  # SIGTERM: nginx's fast shutdown, its workers with it
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def small_scene(tmp: Path) -> Path:
    """The classic scene on a 20 x 20 cloth (cheap on a shared machine), as a TOML file."""
    text = (ASSETS / "scenes" / "classic.toml").read_text()
    assert "\nn = 60\n" in text
    path = tmp / "small.toml"
    path.write_text(text.replace("\nn = 60\n", "\nn = 20\n"))
    return path


@dataclass
class Proxied:
    url: str  # http://127.0.0.1:PROXY/
    ws: str  # ws://127.0.0.1:PROXY/ws
    replay: dict[str, Any]  # a recorded round's index row
    logs: Path  # nginx's directory (access.log)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict[str, Any]]:
    """A data directory holding a recorded round (four bots, fast rounds), and the scene."""
    tmp = tmp_path_factory.mktemp("recorded")
    scene_file = small_scene(tmp)
    data = tmp / "data"
    with web_server(data, scene=Scene.load(scene_file), settings=FAST) as st:
        def rows() -> list[dict[str, Any]]:
            with urllib.request.urlopen(st.url + "api/replays", timeout=10) as r:
                return json.loads(r.read())["replays"]

        row = wait_for(rows, 120, "a round recorded")[-1]
    return data, scene_file, row


@pytest.fixture(scope="module", params=WORKERS, ids=lambda n: f"workers{n}")
def proxied(request: pytest.FixtureRequest, recorded: tuple[Path, Path, dict[str, Any]],
            tmp_path_factory: pytest.TempPathFactory) -> Iterator[Proxied]:
    """``clothball host --workers N`` (two bots in ``main``, the recorded round in its data
    directory) behind nginx."""
    workers = request.param
    data0, scene_file, row = recorded
    tmp = tmp_path_factory.mktemp(f"proxy{workers}")
    data = tmp / "data"
    shutil.copytree(data0, data)
    port = free_port()
    proc, url = start_host(data, "--bots", "2", "--scene", str(scene_file),
                           "--trusted-proxy", "127.0.0.1",
                           "--limit", f"conns_per_address={PER_ADDRESS}",
                           # a test of the proxy: admission must not depend on how much a
                           # loaded test machine has to spare (test_admission.py tests it)
                           "--limit", "admit_lateness_ms=0",
                           port=port, workers=workers)
    assert url is not None, "clothball host did not start"
    try:
        with nginx(tmp / "nginx", port) as proxy:
            yield Proxied(f"http://127.0.0.1:{proxy}/", f"ws://127.0.0.1:{proxy}/ws", row,
                          tmp / "nginx")
    finally:
        stop_host(proc)


@pytest.mark.skipif(bool(NO_BROWSER), reason=NO_BROWSER or "browser present")
def test_the_page_spectates_and_replays_through_the_proxy(proxied: Proxied) -> None:
    drv = make_driver(1100, 720)
    try:
        def js(script: str) -> Any:
            return drv.execute_script(script)

        # The page takes its websocket's address from its own location: the proxy's.
        drv.get(f"{proxied.url}#/room/main")
        wait_for(lambda: js("return document.getElementById('conn').dataset.state") == "open",
                 30, "the page to connect through the proxy")
        wait_for(lambda: js("return window.clothball.stats.meshFrames") > 5, 30,
                 "mesh frames through the proxy")
        def bots() -> int:  # the seats' labels, filled once the room's state has come
            return sum(e.text.startswith("bot-")
                       for e in drv.find_elements("css selector", "#labels .label"))

        wait_for(lambda: bots() >= 2, 30, "the bots' labels")
        labels = [e.text for e in drv.find_elements("css selector", "#labels .label")]
        assert sum(lab.startswith("bot-") for lab in labels) == 2, labels
        # The recorded round: listed, fetched and played through the proxy.
        rid = proxied.replay["id"]
        drv.get(f"{proxied.url}#/replay/{rid}")
        state = lambda: js("const t = document.getElementById('transport');"  # noqa: E731
                           "return [t.dataset.state, Number(t.dataset.time || -1)]")
        wait_for(lambda: state()[0] == "playing", 30, "the replay to play")
        t1 = state()[1]
        wait_for(lambda: state()[1] > t1, 10, "the replay's clock to advance")
        assert js("return window.clothball.replay.duration") == pytest.approx(
            proxied.replay["duration_s"], abs=1e-9)
        drv.get(proxied.url)
        wait_for(lambda: rid in js("return [...document.querySelectorAll('#replays li')]"
                                   ".map(li => li.dataset.id).join(' ')"), 20,
                 "the replay in the page's list")
    finally:
        quit_driver(drv)
    log = (proxied.logs / "access.log").read_text()
    # The page's websocket went through nginx, upgraded (101), and so did the replay.
    assert re.search(r'"GET /ws HTTP/1\.1" 101 ', log), log[-2000:]
    assert re.search(rf'"GET /api/replays/{rid}\S* HTTP/1\.1" 20[06] ', log), log[-2000:]


def test_players_join_main_and_a_created_room_through_the_proxy(proxied: Proxied) -> None:
    async def main() -> None:
        player = await NetClient.connect(proxied.ws, name="p1", role="player", room="main")
        host = await NetClient.connect(proxied.ws, name="maker")
        try:
            assert player.joined is not None and player.joined["room"] == "main"
            made = await host.request("create_room", name="behind a proxy", countdown=0.2)
            joined = await host.join(made["room"], seat=0)
            assert joined["seat"] == 0
            for c in (player, host):
                # Played through the proxy: HIP up, CORNER down, on its one port.
                async def corners(c: NetClient = c) -> None:
                    while c.counts["corner"] < 5:
                        await c.send_hip([0.0, 0.0, 0.0])
                        await asyncio.sleep(0.02)

                await asyncio.wait_for(corners(), 30)
                assert c.url == proxied.ws, f"redirected to {c.url}: a proxy cannot pass it"
        finally:
            await player.close()
            await host.close()

    run(main())


async def _open_from(url: str, source: str, forwarded: str | None = None
                     ) -> websockets.ClientConnection:
    headers = {"X-Forwarded-For": forwarded} if forwarded else None
    return await websockets.connect(url, local_addr=(source, 0),
                                    additional_headers=headers, open_timeout=10)


async def _accepted(ws: websockets.ClientConnection) -> bool:
    """The server kept the connection (a lobby hello answered) or closed it over the
    per-address limit (1008)."""
    try:
        await ws.send(json.dumps({"type": "hello", "version": 1, "name": "x", "id": 0}))
        while True:
            msg = json.loads(await asyncio.wait_for(ws.recv(), 10))
            if msg["type"] == "welcome":
                return True
    except websockets.ConnectionClosed as e:
        assert e.rcvd is not None and e.rcvd.code == 1008, e
        return False


def test_forwarded_for_names_each_client_behind_the_proxy(proxied: Proxied) -> None:
    """Through nginx every connection comes from 127.0.0.1, the trusted proxy: the server
    counts each client by the address nginx writes into X-Forwarded-For, and what a client
    writes there itself does not get it past its limit."""
    async def main() -> None:
        held: list[websockets.ClientConnection] = []
        try:
            for k in range(PER_ADDRESS):  # 127.0.0.2's share, each claiming another address
                ws = await _open_from(proxied.ws, "127.0.0.2", f"203.0.113.{k + 1}")
                held.append(ws)
                assert await _accepted(ws)
            extra = await _open_from(proxied.ws, "127.0.0.2", "198.51.100.9")
            held.append(extra)
            assert not await _accepted(extra)  # over 127.0.0.2's limit, whatever it claims
            other = await _open_from(proxied.ws, "127.0.0.3")
            held.append(other)
            assert await _accepted(other)  # another client: its own count
        finally:
            for ws in held:
                await ws.close()

    run(main())
