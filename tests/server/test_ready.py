"""Ready means ready (issue 40): ``clothball host`` listens before its show room exists (its
bots need the port, the admission's calibration runs meanwhile), so ``/healthz`` says ``ok``
only once ``main`` can be joined, in one process and with gateways. The host is a real
process; the probe asks every 10 ms from the moment the port is chosen and joins ``main``
over a real websocket the moment the first 200 comes."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from clothball.game.net.client import NetClient
from clothball.game.sim.scene import ASSETS
from clothball.server.hostproc import free_port, stop_host

from tests.server.conftest import run

START_S = 120.0  # bound on a host's start on a loaded machine (not a speed claim)


def _healthz(url: str) -> int | None:
    """The status of GET ``url``; None while nothing answers."""
    try:
        with urllib.request.urlopen(url, timeout=5) as r:
            return r.status
    except urllib.error.HTTPError as e:
        with e:
            return e.code
    except (urllib.error.URLError, ConnectionError, TimeoutError):
        return None


@pytest.mark.parametrize("workers", [1, 2], ids=["1proc", "2procs"])
def test_healthz_is_ok_only_once_the_show_room_can_be_joined(tmp_path: Path,
                                                               workers: int) -> None:
    scene = tmp_path / "tiny.toml"
    text = (ASSETS / "scenes" / "classic.toml").read_text()
    scene.write_text(re.sub(r"(?m)^n = \d+", "n = 16", text, count=1))
    port = free_port()
    with open(tmp_path / "host.log", "w") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "clothball.game.cli", "host", "--workers", str(workers),
             "--port", str(port), "--scene", str(scene), "--backend", "cpu", "--data",
             str(tmp_path / "data")], stdout=log, stderr=subprocess.STDOUT,
            env={**os.environ, "OMP_NUM_THREADS": "1"})
        try:
            seen: list[int] = []
            end = time.monotonic() + START_S
            while (status := _healthz(f"http://127.0.0.1:{port}/healthz")) != 200:
                assert proc.poll() is None, (tmp_path / "host.log").read_text()
                assert time.monotonic() < end, f"no 200 from /healthz: {seen[-5:]}"
                if status is not None:
                    seen.append(status)
                time.sleep(0.01)
            assert set(seen) <= {503}, seen  # "starting", never an error

            async def join() -> dict:
                c = await NetClient.connect(f"ws://127.0.0.1:{port}/ws", name="probe")
                try:
                    return await c.join("main", role="spectator")
                finally:
                    await c.close()

            assert run(join())["type"] == "joined"  # not unknown_room
        finally:
            stop_host(proc)
