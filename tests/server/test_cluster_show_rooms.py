"""Two hosts of a cluster started at the same moment each keep a listed show room (issue 33,
item 7): the show room's id is claimed in the directory before the room exists, and a claim
lost to the other host picks another id and tries again. Before, both made ``main``, the
second lost the claim when it published, and its show room was listed nowhere."""

from __future__ import annotations

import asyncio
import subprocess
import time
from contextlib import ExitStack
from pathlib import Path

from clothball.game.net.client import NetClient
from clothball.server.app import GameServer, ServerConfig
from clothball.server.directory import RedisDirectory, SqliteDirectory
from clothball.server.room import RoomSettings

from tests.server.conftest import TINY, no_admission, run, until
from tests.server.test_cluster import cluster_host, launch, pytestmark, redis_server

__all__ = ["pytestmark"]  # skipped where redis-server is missing, as test_cluster.py


def _reaped(proc: subprocess.Popen[str]) -> None:
    """Killed and waited for if still running, its pipe closed."""
    if proc.poll() is None:
        proc.kill()
        proc.wait()
    if proc.stdout is not None:
        proc.stdout.close()


def listed(srv: GameServer) -> set[str]:
    return {r["id"] for r in srv.lobby.rooms_message()["rooms"]}


def test_two_hosts_started_together_both_list_two_show_rooms(tmp_path: Path) -> None:
    """Two servers of one Redis started together in one event loop: each reads the
    directory before either's show room is there, so both would take ``main``."""
    async def main() -> None:
        with redis_server(tmp_path) as redis:
            dirs = [RedisDirectory(redis.url) for _ in range(2)]
            servers = [GameServer(ServerConfig(tmp_path / f"data-{k}", scenes={"tiny": TINY},
                                               backend="cpu", port=0, limits=no_admission(None),
                                               room_settings=RoomSettings(autoplay=True),
                                               host_id=f"host-{k}-ab{k}c"), directory=d)
                       for k, d in enumerate(dirs)]
            try:  # (both stopped below, even when one of them fails to start)
                started = await asyncio.gather(*(s.start() for s in servers),
                                               return_exceptions=True)
                for r in started:
                    if isinstance(r, BaseException):
                        raise r
                ids = {s.main_room.id for s in servers if s.main_room is not None}
                assert ids == {"main", "main-ab0c"} or ids == {"main", "main-ab1c"}, ids
                await until(lambda: all(listed(s) == ids for s in servers), 15,
                            f"both hosts to list {ids}")
                assert [d.conflicts for d in dirs] == [[], []]
            finally:
                await asyncio.gather(*(s.stop() for s in servers))
                for d in dirs:
                    d.close()

    run(main())


def test_two_host_processes_started_at_once_each_keep_a_listed_show_room(tmp_path: Path
                                                                          ) -> None:
    async def lobby(url: str) -> dict[str, str]:
        c = await NetClient.connect(url)
        try:
            rooms = (await c.request("list_rooms"))["rooms"]
        finally:
            await c.close()
        return {r["id"]: r["host"] for r in rooms}

    with redis_server(tmp_path) as redis, ExitStack() as stack:
        procs = []
        for name in ("a", "b"):  # both started before either is waited for
            procs.append(launch(tmp_path, name, redis, "--bots", "1"))
            stack.callback(_reaped, procs[-1])  # (a host cluster_host never took: killed)
        hosts = [stack.enter_context(cluster_host(tmp_path, name, redis, proc=p))
                 for name, p in zip(("a", "b"), procs, strict=True)]

        async def both_listed() -> dict[str, str]:
            for _ in range(100):
                seen = [await lobby(h.url) for h in hosts]
                if all(len(s) == 2 for s in seen):
                    return seen[0]
                await asyncio.sleep(0.1)
            raise AssertionError(f"two show rooms never listed: {seen}")

        rooms = run(both_listed())
        assert "main" in rooms and all(r.startswith("main") for r in rooms)
        assert sorted(rooms.values()) == sorted(h.url for h in hosts)  # one a host
        stack.close()
        for h in hosts:
            assert "is held by host" not in h.out, h.out


def test_the_processes_directory_claims_an_id_for_one_live_process(tmp_path: Path) -> None:
    """SqliteDirectory (the processes of one machine) keeps the same promise."""
    from clothball.server.directory import HostEntry

    d = SqliteDirectory(tmp_path / "rooms.sqlite", ttl=0.5)
    try:
        for h in ("a", "b"):
            d.publish(HostEntry(h, f"ws://{h}/ws"), [])
        assert d.claim("main", "a") and d.claim("main", "a")
        assert not d.claim("main", "b")
        assert "main" not in {r["id"] for r in d.read().listing()}  # claimed, not listed yet
        d.publish(HostEntry("a", "ws://a/ws"), [("main", True, {"id": "main"})])
        assert d.read().locate("main").host_id == "a"  # type: ignore[union-attr]
        assert not d.claim("main", "b")
        time.sleep(0.6)  # a stops publishing: gone after the TTL (a fixed wait past it)
        d.publish(HostEntry("b", "ws://b/ws"), [])
        assert d.claim("main", "b")
    finally:
        d.close()
