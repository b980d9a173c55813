"""A host's engine (``clothball host --workers N``) listens on a loopback port of its own
for its bots (issue 40): a client there would pass the gateways and their per-address
limits, so that port answers only the bots' upgrades (``?house=``), anything else 403
naming the public port. A real engine and gateway; real websocket clients."""

from __future__ import annotations

import asyncio
import json

import pytest
from clothball.game.net.client import NetClient
from clothball.server.room import RoomSettings
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from tests.server import workers
from tests.server.conftest import BACKEND, TINY, http_get_url, no_admission, run, until


@pytest.mark.parametrize("server_processes", [2], indirect=True)
def test_the_engines_own_port_serves_its_bots_and_nobody_else(tmp_path) -> None:
    async def main() -> None:
        async with workers.started(
                tmp_path, scenes={"tiny": TINY}, backend=BACKEND, port=0, bots=2,
                room_settings=RoomSettings(autoplay=True), limits=no_admission(None)) as srv:
            assert srv.public_port is not None and srv.port != srv.public_port
            private = f"127.0.0.1:{srv.port}"
            for path in ("/healthz", "/api/rooms", "/api/stats", "/"):
                status, body, _ = await asyncio.to_thread(http_get_url,
                                                          f"http://{private}{path}")
                assert status == 403, (path, status)
                assert f"public port {srv.public_port}" in json.loads(body)["error"]
            for url in (f"ws://{private}/ws", f"ws://{private}/ws?house=nope"):
                with pytest.raises(InvalidStatus) as refused:
                    async with connect(url):
                        pass
                assert refused.value.response.status_code == 403
            # Its bots come in all the same (the house key), and players by the public port.
            room = srv.main_room
            assert room is not None
            bots = [s for s in room.seats if s.kind == "bot"]
            assert len(bots) == 2
            await until(lambda: all(s.conn is not None for s in bots), 60, "bots connected")
            public = f"http://127.0.0.1:{srv.public_port}/healthz"
            assert (await asyncio.to_thread(http_get_url, public))[0] == 200
            c = await NetClient.connect(srv.ws_url, role="spectator", room="main")
            await c.close()

    run(main())
