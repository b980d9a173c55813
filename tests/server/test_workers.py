"""``clothball host --workers 2``: two real server processes on one port. Any connection sees
every process's rooms; a join, a watch or a new room that the other process serves is
redirected there and the client follows; the kernel spreads connections over both."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from clothball.game.net.client import NetClient
from clothball.game.sim.scene import ASSETS

from tests.server.conftest import run, until


@contextmanager
def host(tmp_path: Path, *args: str) -> Iterator[str]:
    """``clothball host --workers 2`` on a free port (a 16x16 classic cloth); yields its URL."""
    scene = tmp_path / "tiny.toml"
    text = (ASSETS / "scenes" / "classic.toml").read_text()
    scene.write_text(re.sub(r"(?m)^n = \d+", "n = 16", text, count=1))
    proc = subprocess.Popen(
        [sys.executable, "-m", "clothball.game.cli", "host", "--workers", "2", "--port", "0",
         "--scene", str(scene), "--backend", "cpu", "--data", str(tmp_path / "data"),
         "--limit", "admit_lateness_ms=0", *args],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.stdout is not None
    url = None
    lines = []
    for line in proc.stdout:
        lines.append(line)
        m = re.match(r"clothball server on (ws://\S+)\s+\(2 processes", line)
        if m:
            url = m.group(1)
            break
    try:
        assert url is not None, "".join(lines)
        yield url
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=60)
        assert proc.returncode == 0, "".join(lines) + out
        assert "Traceback" not in out, out


def test_two_processes_share_one_lobby_and_send_clients_where_rooms_live(tmp_path) -> None:
    async def main(url: str) -> None:
        lobby = await NetClient.connect(url, name="lobby")
        rooms = (await lobby.request("list_rooms"))["rooms"]
        assert [r["id"] for r in rooms] == ["main"]
        main_host = rooms[0]["host"]
        # The first room goes to the process without one, whichever process was asked.
        made = []
        for i in range(2):
            c = await NetClient.connect(url, name=f"maker{i}")
            reply = await c.request("create_room", name=f"r{i}", bots_allowed=False,
                                    unguarded=True)
            made.append((c, reply["room"]))
        await until(lambda: len(lobby.messages) > 0, 5)

        async def listing() -> dict[str, str]:
            got = (await lobby.request("list_rooms"))["rooms"]
            return {r["id"]: r["host"] for r in got}

        want = {"main", made[0][1], made[1][1]}
        for _ in range(100):
            hosts = await listing()
            if set(hosts) == want:
                break
            await asyncio.sleep(0.1)
        assert set(hosts) == want, hosts
        # Two processes, each with rooms: main and one new room, then the other new room.
        assert len(set(hosts.values())) == 2
        assert hosts[made[0][1]] != main_host
        # Watchers of every room, from connections the kernel spreads over both processes:
        # each ends up on the room's own process (followed redirects) and gets its meshes.
        redirected = 0
        for rid in want:
            for k in range(3):
                w = await NetClient.connect(url, name=f"w{k}", role="spectator", room=rid)
                assert w.room == rid and w.url in (url, hosts[rid])
                redirected += w.url != url
                await until(lambda w=w: w.mesh is not None, 10, f"a mesh of {rid}")
                assert w.mesh.positions.shape == (16, 16, 3)
                await w.close()
        assert redirected > 0
        # A player takes a bot's corner in main wherever its connection landed, and plays.
        p = await NetClient.connect(url, name="ann", role="player", room="main", seat=2)
        assert p.seat == 2 and p.joined["kind"] == "human"
        hip = np.array(p.reach.centre) + [0.0, 0.02, 0.0]
        for _ in range(50):
            await p.send_hip(hip)
            await asyncio.sleep(0.002)
        await until(lambda: p.corner is not None and p.corner.hip_seq > 0, 10, "an echo")
        await p.close()
        for c, _ in made:
            await c.close()
        await lobby.close()

    with host(tmp_path, "--bots", "4") as url:
        run(main(url))
