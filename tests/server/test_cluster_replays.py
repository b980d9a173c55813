"""Replays in a cluster: three ``clothball host --cluster redis://... --db postgresql://...``
processes on loopback with a real Redis and a real PostgreSQL, both started here on free
ports. A round scored on one host is listed by another and downloaded through it (a 307 to
the host that holds the file, followed by the client); PostgreSQL stopped mid-match loses
nothing (the round is kept as a file, the lobby and /api/stats say the index is away, the
row appears once it is back); a host SIGKILLed under its clients sends them back to the
lobby of the host they came from with a message naming the room, while the others' rooms
run on."""

from __future__ import annotations

import asyncio
import json
import urllib.error
import urllib.request
from contextlib import ExitStack
from typing import Any

import pytest
from clothball.game.client.replay import fetch
from clothball.game.net.client import NetClient
from clothball.game.wire.replay import read_replay
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from tests.server.conftest import run, until
from tests.server.postgres import MISSING, postgres_server
from tests.server.test_cluster import REDIS, cluster_host, redis_server, wait_published

pytestmark = [
    pytest.mark.skipif(REDIS is None, reason="needs redis-server (apt: redis-server)"),
    pytest.mark.skipif(MISSING is not None, reason=str(MISSING)),
]


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, *args: Any, **kw: Any) -> None:
        return None  # the 307 itself, not where it leads


def http_of(ws_url: str) -> str:
    return ws_url.replace("ws://", "http://", 1)[: -len("/ws")]


def get(url: str, follow: bool = True) -> tuple[int, bytes, dict[str, str]]:
    opener = urllib.request.build_opener() if follow else \
        urllib.request.build_opener(_NoRedirect)
    try:
        with opener.open(url, timeout=10) as r:
            return r.status, r.read(), dict(r.headers)
    except urllib.error.HTTPError as e:
        with e:
            return e.code, e.read(), dict(e.headers)


def listed(ws_url: str) -> dict[str, dict[str, Any]]:
    status, body, _ = get(f"{http_of(ws_url)}/api/replays?limit=1000")
    assert status == 200, body
    return {r["id"]: r for r in json.loads(body)["replays"]}


def stats(ws_url: str) -> dict[str, Any]:
    return json.loads(get(f"{http_of(ws_url)}/api/stats")[1])


def test_replays_shared_through_postgresql_across_hosts_and_failures(tmp_path) -> None:
    with ExitStack() as stack:
        redis = stack.enter_context(redis_server(tmp_path))
        pg = stack.enter_context(postgres_server())
        extra = ("--db", pg.url, "--limit", "storage_check_s=0.5")
        hosts = [stack.enter_context(cluster_host(tmp_path, k, redis, *extra))
                 for k in ("a", "b", "c")]
        by_url = {h.url: h for h in hosts}

        async def main() -> None:
            # A room of four bots throwing fast rounds, on whichever host placement picks.
            owner = await NetClient.connect(hosts[0].url, name="owner")
            await wait_published(redis, lambda hs: len(hs) == 3, "every host's load")
            made = await owner.request("create_room", name="rounds", first_to=99,
                                       countdown=0.2, reset_speed=3.0, autoplay=True,
                                       restart_delay=30)
            rid = made["room"]
            x = by_url[owner.url]  # the room's host
            y, z = [h for h in hosts if h is not x]
            # A page served by x that followed a redirect here is let in; another site's not.
            async with connect(y.url, origin=http_of(x.url)):  # type: ignore[arg-type]
                pass
            with pytest.raises(InvalidStatus) as refused:
                async with connect(y.url, origin="http://elsewhere.example"):  # type: ignore[arg-type]
                    pass
            assert refused.value.response.status_code == 403
            await owner.join(rid, role="spectator")
            for _ in range(4):
                await owner.request("add_bot")
            # A spectator that came in through y, sent to x for the room.
            watcher = await NetClient.connect(y.url, name="watcher", role="spectator",
                                              room=rid)
            assert watcher.url == x.url and watcher.home == y.url
            saved = await watcher.wait_event("replay_saved", timeout=60, since=0)
            first = saved["id"]

            # Listed by every host, saying which holds the file; downloaded through y.
            for h in (y, z):
                row = listed(h.url)[first]
                assert row["host"] == http_of(x.url) and row["room_id"] == rid
            direct = get(f"{http_of(x.url)}/api/replays/{first}")
            assert direct[0] == 200
            assert direct[1] == (tmp_path / f"data-{'abc'[hosts.index(x)]}" / "replays" /
                                 f"{first}.cbr").read_bytes()
            status, _, head = get(f"{http_of(y.url)}/api/replays/{first}", follow=False)
            assert status == 307
            assert head["Location"] == f"{http_of(x.url)}/api/replays/{first}.cbr"
            status, body, _ = get(f"{http_of(y.url)}/api/replays/{first}")
            assert status == 200 and body == direct[1]
            # What `clothball replay ID --server` fetches, through another host.
            assert await asyncio.to_thread(fetch, first, z.url) == direct[1]
            assert read_replay(body)[0]["id"] == first

            # PostgreSQL stops mid-match: the next round is kept as a file, x says the index
            # is away (lobby and /api/stats); the row appears once it is back.
            before = listed(z.url)
            await asyncio.to_thread(pg.stop)
            mark = watcher.received_total
            during = await watcher.wait_event("replay_saved", timeout=60, since=mark)
            assert (tmp_path / f"data-{'abc'[hosts.index(x)]}" / "replays" /
                    f"{during['id']}.cbr").is_file()
            assert stats(x.url)["replay_index"].startswith("unavailable: the replay index")
            lobby_x = await NetClient.connect(x.url, name="lobby-x")
            assert "PostgreSQL" in (await lobby_x.request("list_rooms"))["replay_index_error"]
            await asyncio.to_thread(pg.start)
            await until(lambda: during["id"] in listed(y.url), 20, "the kept round indexed")
            after = listed(y.url)
            assert set(before) <= set(after)
            assert all(after[k] == v for k, v in before.items())
            await until(lambda: stats(x.url)["replay_index"] == "ok", 10, "the index back")
            assert "replay_index_error" not in await lobby_x.request("list_rooms")
            await lobby_x.close()

            # x dies with clients in its room: the watcher is told which room's host went
            # away and is back in y's lobby; z's show room runs on.
            main_z = next(r["id"] for r in (await owner.request("list_rooms"))["rooms"]
                          if r["host"] == z.url)
            watch_z = await NetClient.connect(y.url, name="wz", role="spectator", room=main_z)
            await until(lambda: watch_z.counts["mesh"] > 5, 10, "z's room streams")
            mark = watcher.received_total
            x.proc.kill()
            gone = await watcher.wait_for(lambda m: m["type"] == "host_gone", 15, since=mark)
            assert gone["room"] == rid and gone["url"] == x.url
            assert f"the host of room {rid} went away" in gone["message"]
            assert watcher.url == y.url and watcher.room is None
            with pytest.raises(TimeoutError):  # alive, in y's lobby
                await watcher.wait_closed(timeout=0.5)
            rooms = (await watcher.request("list_rooms"))["rooms"]
            assert main_z in [r["id"] for r in rooms]
            n = watch_z.counts["mesh"]
            await until(lambda: watch_z.counts["mesh"] > n + 10, 10, "z's room runs on")
            # What x stored stays listed by the others (its file comes back with x).
            assert {first, during["id"]} <= set(listed(z.url))
            for cl in (owner, watcher, watch_z):
                await cl.close()

        run(main(), timeout=200)
