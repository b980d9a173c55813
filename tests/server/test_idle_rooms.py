"""A room with no human player and no spectator sleeps (no stepping) and wakes at once for
the next one who comes in; the host's own show room does too, and also steps for a while after
someone lists the rooms."""

from __future__ import annotations

import asyncio

from clothball.game.net.client import NetClient
from clothball.server.limits import Limits
from clothball.server.room import RoomSettings

from tests.server.conftest import run, server, until


def test_an_empty_room_sleeps_and_wakes_for_a_spectator(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path, settings=RoomSettings(autoplay=True)) as srv:
            main_room = srv.main_room
            # The show room with no one in it and no bots sleeps like any room (issue 31),
            # until someone lists the rooms (a lobby client's welcome does).
            assert main_room is not None
            await until(lambda: main_room.sim.asleep, 5, "the empty show room asleep")
            f_main = main_room.sim.stats.frames
            await asyncio.sleep(0.3)  # (a fixed wait on purpose: no frame in it)
            assert main_room.sim.stats.frames == f_main
            owner = await NetClient.connect(srv.ws_url)
            assert not main_room.sim.asleep
            await until(lambda: main_room.sim.stats.frames > f_main + 100, 10,
                        "the listed show room steps")
            rid = (await owner.request("create_room", name="quiet"))["room"]
            room = srv.lobby.rooms[rid]
            assert room.sim.asleep  # nobody in it: it does not step
            f0 = room.sim.stats.frames
            await asyncio.sleep(0.3)  # (a fixed wait on purpose: no frame in it)
            assert room.sim.stats.frames == f0
            spec = await NetClient.connect(srv.ws_url, role="spectator", room=rid)
            assert not room.sim.asleep
            await until(lambda: room.sim.stats.frames > f0 + 100, 10, "the room steps again")
            # the slept time is not replayed: nothing skipped, no burst of catch-up frames
            assert room.sim.stats.skipped_frames == 0
            await until(lambda: spec.mesh is not None, 10, "a mesh for the spectator")
            await spec.request("leave")
            await until(lambda: room.sim.asleep, 5, "asleep again")
            f1 = room.sim.stats.frames
            await asyncio.sleep(0.3)  # (a fixed wait on purpose: no frame in it)
            assert room.sim.stats.frames == f1
            player = await NetClient.connect(srv.ws_url, name="ann", role="player", room=rid)
            assert not room.sim.asleep and player.seat is not None
            assert not main_room.sim.asleep
            for c in (owner, spec, player):
                await c.close()

    run(main())


def test_an_abandoned_room_closes_after_the_idle_delay_and_a_watched_one_stays(tmp_path) -> None:
    async def main() -> None:
        limits = Limits().replace(room_idle_close_s=1.0)
        async with server(tmp_path, limits=limits) as srv:
            owner = await NetClient.connect(srv.ws_url)
            gone = (await owner.request("create_room", name="abandoned"))["room"]
            kept = (await owner.request("create_room", name="watched"))["room"]
            spec = await NetClient.connect(srv.ws_url, role="spectator", room=kept)
            t0 = asyncio.get_running_loop().time()
            await until(lambda: gone not in srv.lobby.rooms, 10, "the abandoned room closed")
            # Not before its delay (checked each second), and the watched room stays open.
            assert asyncio.get_running_loop().time() - t0 >= 1.0
            await asyncio.sleep(2.5)  # (a fixed wait on purpose: past the delay, still open)
            assert kept in srv.lobby.rooms and srv.main_room is not None
            # The room list says so: the closed room is no longer offered.
            ids = [r["id"] for r in (await owner.request("list_rooms"))["rooms"]]
            assert gone not in ids and kept in ids
            for c in (owner, spec):
                await c.close()

    run(main())
