"""Bots are backfill: in a room full of bots a human who joins takes a bot's seat (the bot
leaves at once, and the seat event says so); the room's listing says which corners a human
may take; a seat held by a human is never taken."""

from __future__ import annotations

from typing import Any

from clothball.game.net.client import NetClient, ServerError
from clothball.server.room import RoomSettings

from tests.server.conftest import run, server, until


async def four_bots_seated(srv: Any) -> Any:
    """The demo room of a server started with four bots, once they all sit in it."""
    room = srv.main_room
    assert room is not None
    await until(lambda: all(s.kind == "bot" and s.connected for s in room.seats), 20,
                "four bots seated")
    return room


def test_a_human_takes_a_bots_seat_in_the_demo_room(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path, bots=4, settings=RoomSettings(autoplay=True)) as srv:
            room = await four_bots_seated(srv)
            lobby = await NetClient.connect(srv.ws_url)
            listed = (await lobby.request("list_rooms"))["rooms"][0]["seats"]
            assert [s["open"] for s in listed] == [True] * 4  # every bot's corner can be taken
            spectator = await NetClient.connect(srv.ws_url, role="spectator", room="main")
            ann = await NetClient.connect(srv.ws_url, name="ann", role="player", room="main")
            assert ann.seat == 0 and room.seats[0].kind == "human"
            ev = await spectator.wait_event("seat", timeout=10, since=0,
                                            reason="replaced_bot")
            assert ev["seat"] == 0 and ev["name"] == "ann" and ev["kind"] == "human"
            bob = await NetClient.connect(srv.ws_url, name="bob", role="player", room="main",
                                          seat=2)
            assert bob.seat == 2 and room.seats[2].name == "bob"
            assert [s.kind for s in room.seats] == ["human", "bot", "human", "bot"]
            await until(lambda: len(srv.clients) == 6, 10, "two bots gone: 4 clients, 2 bots")
            state = (await lobby.request("list_rooms"))["rooms"][0]["seats"]
            assert [s["open"] for s in state] == [False, True, False, True]
            # a human's seat is not for the taking
            try:
                await NetClient.connect(srv.ws_url, name="cy", role="player", room="main",
                                        seat=0)
            except ServerError as e:
                assert e.code == "bad_seat" and "player" in str(e)
            else:
                raise AssertionError("took a human's seat")
            # the room plays on with its humans and bots
            f0 = room.sim.stats.frames
            await until(lambda: room.sim.stats.frames > f0 + 100, 10, "frames go on")
            for c in (lobby, spectator, ann, bob):
                await c.close()

    run(main())


def test_the_first_corner_after_taking_a_bots_seat_echoes_no_hip_of_the_bot(tmp_path) -> None:
    """docs/protocol.md: a CORNER's ``seq`` is the last HIP the server applied for this
    seat. A human who takes a bot's seat has sent none yet: every CORNER before their
    first HIP says seq 0 (no time), never the bot's seq and time; after it, their own."""
    import math

    async def main() -> None:
        async with server(tmp_path, bots=4, settings=RoomSettings(autoplay=True)) as srv:
            room = await four_bots_seated(srv)
            # the bots' HIPs are being applied (their seq echoes in the room's corners)
            await until(lambda: room.sim.hip_echo(0)[0] > 0, 10, "the bot's HIPs applied")
            ann = await NetClient.connect(srv.ws_url, name="ann")
            got: list = []
            ann.on_corner = got.append
            await ann.join("main", seat=0)
            await until(lambda: len(got) >= 20, 10, "corners for the new occupant")
            before = list(got)
            assert all(c.seat == 0 for c in before)
            assert all(c.hip_seq == 0 and math.isnan(c.hip_time) for c in before), [
                (c.hip_seq, c.hip_time) for c in before if c.hip_seq != 0][:3]
            await ann.send_hip(room.anchors[0])
            await until(lambda: got[-1].hip_seq == 1, 10, "ann's own HIP echoed")
            assert all(c.hip_seq in (0, 1) for c in got)
            await ann.close()

    run(main())
