"""A match never starts with unguarded edges unless the room asks for it: pressing ready
alone in one's own room fills the empty seats with bots (the room allows them); a room with
no bots does not start and says why; a room that asks for empty seats starts as it is."""

from __future__ import annotations

from typing import Any

import pytest
from clothball.game.client.model import ClientModel
from clothball.game.net.client import NetClient, ServerError
from clothball.server.app import GameServer
from clothball.server.room import Room

from tests.server.conftest import run, server, until


async def alone_in_own_room(srv: GameServer, **opts: Any) -> tuple[NetClient, Room]:
    """ann creates a room with these settings and sits on corner 0, alone."""
    ann = await NetClient.connect(srv.ws_url, name="ann")
    rid = (await ann.request("create_room", name="mine", **opts))["room"]
    await ann.join(rid, seat=0)
    return ann, srv.lobby.rooms[rid]


def test_ready_alone_fills_empty_seats_with_bots(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path, default_room=False) as srv:
            ann, room = await alone_in_own_room(srv, countdown=0.2)
            await ann.request("ready", ready=True)
            await until(lambda: room.match.state != "waiting", 10, "match started")
            assert [s.kind for s in room.seats] == ["human", "bot", "bot", "bot"]
            ev = await ann.wait_event("seat", timeout=10, since=0, reason="backfill")
            assert ev["kind"] == "bot"
            await until(lambda: all(s.connected for s in room.seats), 20, "bots connected")
            await until(lambda: room.match.round >= 1, 20, "a round is played")
            await ann.close()

    run(main())


def test_no_bots_room_does_not_start_and_says_why(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path, default_room=False) as srv:
            ann, room = await alone_in_own_room(srv, bots_allowed=False)
            await ann.request("ready", ready=True)
            ev = await ann.wait_event("cannot_start", timeout=10, since=0)
            assert "1, 2, 3" in ev["reason"] and "no bots" in ev["reason"]
            model = ClientModel(name="ann")  # the desktop client's log line for it
            model.apply(ev, 0.0)
            assert model.events[-1].text == f"cannot start: {ev['reason']}"
            with pytest.raises(ServerError) as e:
                await ann.request("start")
            assert e.value.code == "cannot_start" and "wait for players" in str(e.value)
            assert room.match.state == "waiting"
            assert [s.kind for s in room.seats] == ["human", "empty", "empty", "empty"]
            await ann.close()

    run(main())


def test_a_room_that_asks_for_empty_seats_starts_as_it_is(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path, default_room=False) as srv:
            ann, room = await alone_in_own_room(srv, unguarded=True, countdown=0.2)
            await ann.request("ready", ready=True)
            await until(lambda: room.match.state != "waiting", 10, "match started")
            assert [s.kind for s in room.seats] == ["human", "empty", "empty", "empty"]
            await ann.close()

    run(main())
