"""Three ``clothball host --cluster redis://...`` processes on loopback with a real Redis
(started here on a free port): one lobby over all hosts, rooms placed on the least-loaded
host, joins and watches followed across hosts, a host killed with SIGKILL leaving the
directory within the TTL while the others run on, Redis stopped and restarted, and the
killed host restarted, joining again."""

from __future__ import annotations

import asyncio
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import pytest
from clothball.game.net.client import NetClient
from clothball.game.sim.scene import ASSETS
from clothball.server.directory import RedisDirectory
from clothball.server.hostproc import free_port, start_redis

from tests.server.conftest import run, until

REDIS = shutil.which("redis-server")
pytestmark = pytest.mark.skipif(REDIS is None, reason="needs redis-server (apt: redis-server)")


class Redis:
    """A redis-server of the test's own, on a free port, no persistence."""

    def __init__(self, tmp: Path) -> None:
        self.port = free_port()
        self.dir = tmp
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        assert REDIS is not None
        self.proc = start_redis(REDIS, self.port, self.dir)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:  # (a SIGSTOPped one too): never left running
                self.proc.kill()
                self.proc.wait()
                raise


@contextmanager
def redis_server(tmp: Path) -> Iterator[Redis]:
    r = Redis(tmp)
    r.start()
    try:
        yield r
    finally:
        r.stop()


def tiny_scene(tmp: Path) -> Path:
    scene = tmp / "tiny.toml"
    text = (ASSETS / "scenes" / "classic.toml").read_text()
    scene.write_text(re.sub(r"(?m)^n = \d+", "n = 16", text, count=1))
    return scene


class Host:
    def __init__(self, proc: subprocess.Popen[str], url: str) -> None:
        self.proc = proc
        self.url = url
        self.out = ""  # what it printed, once stopped


def launch(tmp: Path, name: str, redis: Redis, *args: str) -> subprocess.Popen[str]:
    """A ``clothball host`` of the cluster, started (``cluster_host`` waits for it)."""
    return subprocess.Popen(
        [sys.executable, "-m", "clothball.game.cli", "host", "--workers", "1", "--port", "0",
         "--cluster", redis.url, "--scene", str(tiny_scene(tmp)), "--backend", "cpu",
         "--data", str(tmp / f"data-{name}"), "--limit", "admit_lateness_ms=0", *args],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"})


@contextmanager
def cluster_host(tmp: Path, name: str, redis: Redis, *args: str,
                 proc: subprocess.Popen[str] | None = None) -> Iterator[Host]:
    """The host ``launch`` starts (or ``proc``, launched already) once it is in the
    cluster; stopped with SIGTERM at the end, which it must survive cleanly. What it printed
    is kept in ``Host.out``."""
    proc = proc or launch(tmp, name, redis, *args)
    assert proc.stdout is not None
    lines = []
    url = None
    host = Host(proc, "")
    try:  # (stopped below even when reading its first lines fails)
        for line in proc.stdout:
            lines.append(line)
            m = re.match(r"clothball server on (ws://\S+)", line)
            if m:
                url = m.group(1)
            if line.startswith("in the cluster at"):
                break
        host.url = url or ""
        assert url is not None, "".join(lines)
        yield host
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            out, _ = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:  # never left running, whatever the test found
            proc.kill()
            out, _ = proc.communicate()
            out += "\n(killed: it did not stop within 60 s of SIGTERM)"
        host.out = "".join(lines) + out
        if proc.returncode != -signal.SIGKILL:  # a host the test killed says nothing more
            assert proc.returncode == 0 and "Traceback" not in out, out


async def hosts_of(c: NetClient) -> dict[str, str]:
    reply = await c.request("list_rooms")
    return {r["id"]: r["host"] for r in reply["rooms"]}


async def wait_published(redis: Redis, pred, what: str, timeout: float = 15.0) -> None:
    """Until the hosts' entries in the directory (address -> HostEntry, as every host reads
    them: ``RedisDirectory.read``) satisfy ``pred``: a wait for the loads placement reads,
    not a fixed time for their publication."""
    d = RedisDirectory(redis.url)
    try:
        end = time.monotonic() + timeout
        while True:
            hosts = {h.address: h for h in (await asyncio.to_thread(d.read)).hosts.values()}
            if pred(hosts):
                return
            assert time.monotonic() < end, f"timed out waiting for {what}: {hosts}"
            await asyncio.sleep(0.1)
    finally:
        d.close()


async def wait_listing(c: NetClient, pred, what: str, timeout: float = 15.0) -> dict[str, str]:
    end = time.monotonic() + timeout
    while True:
        got = await hosts_of(c)
        if pred(got):
            return got
        assert time.monotonic() < end, f"timed out waiting for {what}: {got}"
        await asyncio.sleep(0.1)


def test_three_hosts_one_lobby_placement_redirects_and_failures(tmp_path) -> None:
    with ExitStack() as stack:
        redis = stack.enter_context(redis_server(tmp_path))
        hosts = [stack.enter_context(cluster_host(tmp_path, k, redis, "--bots", "4"))
                 for k in ("a", "b", "c")]
        a, b, c = hosts

        async def main() -> None:
            la = await NetClient.connect(a.url, name="lobby-a")
            # Every host's show room, listed from any host, each where it lives.
            listing = await wait_listing(la, lambda h: len(h) == 3, "three show rooms")
            assert set(listing.values()) == {h.url for h in hosts}
            assert "main" in listing
            # New rooms go to the least-loaded host (rooms, then clients): with one room on
            # every host the first goes to one with the fewest clients; the second, asked of
            # that one (the client followed the redirect, if any), goes to another, since
            # that one now has two rooms. (Each host republishes its load every 0.5 s: the
            # test waits until the directory holds the loads placement reads.)
            maker = await NetClient.connect(a.url, name="maker")
            await wait_published(redis, lambda hs: set(hs) == {h.url for h in hosts} and all(
                e.rooms == 1 for e in hs.values()), "every host's one room published")
            r1 = (await maker.request("create_room", name="r1", bots_allowed=False,
                                      unguarded=True))["room"]
            first = maker.url
            await wait_published(redis, lambda hs: first in hs and hs[first].rooms == 2,
                                 "r1's host's load")
            r2 = (await maker.request("create_room", name="r2", bots_allowed=False,
                                      unguarded=True))["room"]
            listing = await wait_listing(la, lambda h: r1 in h and r2 in h, "the new rooms")
            assert listing[r1] == first and listing[r2] == maker.url != first
            # Watching and playing across hosts.
            for rid, where in listing.items():
                w = await NetClient.connect(a.url, name="w", role="spectator", room=rid)
                assert w.room == rid and w.url == where
                await until(lambda w=w: w.mesh is not None, 10, f"a mesh of {rid}")
                await w.close()
            main_b = next(r for r, u in listing.items() if u == b.url and r.startswith("main"))
            watcher_b = await NetClient.connect(a.url, name="wb", role="spectator", room=main_b)
            # Host c dies (SIGKILL): it leaves the directory within the TTL (5 s); the others'
            # rooms run on.
            c_rooms = {r for r, u in listing.items() if u == c.url}
            assert c_rooms
            c.proc.kill()
            t0 = time.monotonic()
            await wait_listing(la, lambda h: not (c_rooms & set(h)), "c's rooms gone", 10)
            assert time.monotonic() - t0 <= 5.0 + 1.5  # (the TTL's bound, and a read's lag)
            n0 = watcher_b.counts["mesh"]
            await until(lambda: watcher_b.counts["mesh"] > n0 + 10, 10, "b's room runs on")
            # Redis stops: hosts keep their rooms, the lobby says the directory is away.
            redis.stop()

            async def directory_away() -> dict:
                end = time.monotonic() + 10
                while True:
                    reply = await la.request("list_rooms")
                    if "directory_error" in reply or time.monotonic() > end:
                        return reply
                    await asyncio.sleep(0.1)

            reply = await directory_away()
            assert "unavailable" in reply.get("directory_error", "")
            assert {r["host"] for r in reply["rooms"]} <= {a.url}
            n1 = watcher_b.counts["mesh"]
            await until(lambda: watcher_b.counts["mesh"] > n1 + 10, 10, "b runs without Redis")
            # Redis is back (empty): every host registers again by itself.
            redis.start()
            alive = {r: u for r, u in listing.items() if u != c.url}
            back = await wait_listing(la, lambda h: set(alive) <= set(h),
                                      "the hosts registered again")
            assert {r: back[r] for r in alive} == alive
            reply = await la.request("list_rooms")
            assert "directory_error" not in reply and back[main_b] == b.url
            # Host c restarted (its data directory as before) joins again: its show room is
            # listed from the others, and none of the dead process's rooms comes back.
            c2 = await asyncio.to_thread(stack.enter_context,
                                         cluster_host(tmp_path, "c", redis, "--bots", "4"))
            again = await wait_listing(la, lambda h: c2.url in h.values(), "c back")
            assert not (c_rooms & set(again))
            for cl in (la, maker, watcher_b):
                await cl.close()

        run(main(), timeout=150)
