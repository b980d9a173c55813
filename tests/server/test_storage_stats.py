"""``/api/stats``: resetting it needs the host's token (issue 21); everything else in it is
public."""

from __future__ import annotations

import asyncio
import json
import stat
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

from clothball.server.room import RoomSettings

from tests.server.conftest import http_json, run, server, until


def get(url: str, token: str | None = None) -> tuple[int, Any]:
    req = urllib.request.Request(url, headers={"Authorization": token} if token else {})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        with e:
            return e.code, json.loads(e.read())


def test_only_the_host_token_resets_the_statistics(tmp_path: Path) -> None:
    async def main() -> None:
        async with server(tmp_path, settings=RoomSettings(autoplay=True)) as srv:
            token_file = tmp_path / "host-token"
            assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
            token = token_file.read_text().strip()
            assert token == srv.host_token and len(token) >= 32

            def lateness() -> int:
                assert srv.main_room is not None
                return len(srv.main_room.sim.stats.lateness)

            url = srv.http_url + "api/stats?reset=1"
            await http_json(srv, "/api/rooms")  # listed: the empty show room steps a while
            await until(lambda: lateness() > 50, 30, "frames timed")
            for bad in (None, "Bearer nope", f"Basic {token}", f"Bearer {token}x", token):
                before = lateness()
                status, body = await asyncio.to_thread(get, url, bad)
                assert status == 403 and "host's token" in body["error"], bad
                assert lateness() >= before  # nothing was cleared
            for spelled in (f"Bearer {token}", f"bearer  {token} "):
                await until(lambda: lateness() > 50, 30, "frames timed")
                status, body = await asyncio.to_thread(get, url, spelled)
                assert status == 200 and "rooms" in body
                assert lateness() < 50  # cleared (a few frames may have come since)
            public = await http_json(srv, "/api/stats")
            assert "host_token" not in json.dumps(public) and token not in json.dumps(public)

    run(main())


def test_a_given_host_token_is_used_and_written(tmp_path: Path) -> None:
    async def main() -> None:
        async with server(tmp_path, default_room=False, host_token="tok-" + "x" * 30) as srv:
            assert (tmp_path / "host-token").read_text().strip() == srv.host_token
            status, _ = await asyncio.to_thread(get, srv.http_url + "api/stats?reset",
                                                "Bearer tok-" + "x" * 30)
            assert status == 200

    run(main())


def test_the_servers_of_one_data_directory_share_the_token(tmp_path: Path) -> None:
    """Servers of one data directory (an engine and the engine restarted after it, two
    servers of a test) share its token: whichever of them answers, the one token in
    DATA/host-token resets the statistics; a restart keeps it, and deleting the file
    makes a new one."""
    async def main() -> None:
        async with server(tmp_path, default_room=False) as a, \
                server(tmp_path, default_room=False) as b:
            token = (tmp_path / "host-token").read_text().strip()
            assert a.host_token == b.host_token == token
            for srv in (a, b):
                status, _ = await asyncio.to_thread(get, srv.http_url + "api/stats?reset=1",
                                                    f"Bearer {token}")
                assert status == 200
        async with server(tmp_path, default_room=False) as again:
            assert again.host_token == token
        (tmp_path / "host-token").unlink()
        async with server(tmp_path, default_room=False) as fresh:
            assert fresh.host_token != token
            assert (tmp_path / "host-token").read_text().strip() == fresh.host_token
            assert not list(tmp_path.glob(".host-token-*"))

    run(main())
