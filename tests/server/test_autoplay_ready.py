"""A human who takes a seat in an autoplay room while it waits to restart, and says ready,
starts the next match when the wait is over (the ready was lost: the match never came)."""

from __future__ import annotations

from clothball.game.net.client import NetClient
from clothball.server.room import RoomSettings

from tests.server.conftest import FAST, run, server, until


def test_a_ready_said_during_the_restart_wait_starts_the_next_match(tmp_path) -> None:
    async def main() -> None:
        settings = RoomSettings(**{**FAST, "first_to": 1, "restart_delay": 3.0},
                                autoplay=True)
        async with server(tmp_path, bots=4, settings=settings) as srv:
            room = srv.main_room
            assert room is not None
            await until(lambda: room.match.state == "over", 60, "the bots' match over")
            # During the restart wait: a human takes a bot's corner and says ready.
            ann = await NetClient.connect(srv.ws_url, name="ann", role="player",
                                          room="main", seat=0)
            assert ann.joined is not None and ann.joined["kind"] == "human"
            assert room.match.state == "over" and room._task is not None
            since = ann.received_total
            await ann.request("ready", ready=True)
            ev = await ann.wait_event("match_start", timeout=15, since=since)
            assert ev["seats"]  # the seated players, ann among them
            await until(lambda: room.match.state in ("countdown", "playing"), 5, "playing")
            await ann.close()

    run(main())
