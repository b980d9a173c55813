"""The lane code (server/lanes/lane.py) that serves every seated player's HIPs and CORNERs
and every client's MESH, in the engine and in a gateway alike: a CORNER made from a former
occupant's hand is never sent to the seat's new occupant, whatever the timing."""

from __future__ import annotations

import asyncio
import math

from clothball.game.wire import protocol as P
from clothball.server.lanes.lane import Lane
from clothball.server.lanes.local import LocalLinks
from clothball.server.shared.lanes import LaneSpec

from tests.server.conftest import run, started_room, until


def test_a_corner_of_the_former_occupants_hand_is_not_sent_to_the_new_one() -> None:
    """Seat 2's hand is its occupant's (seq 41) in the newest frame; the seat changes hands
    while the frame loop is held between two passes, and the new occupant's lane opens then:
    the newest CORNER (the former occupant's HIP echoed) is not sent; once the loop steps
    on, the new occupant's CORNERs come, echoing no HIP."""
    async def main() -> None:
        with started_room() as sim:
            w = sim.worker
            links = LocalLinks(sim.pool.local_shares, sim.pool.set_wake)
            view = links.block(w.block_id)
            slot, seat = sim.slot, 2
            old = sim.occupant[seat]
            assert view.write_hip(slot, seat, old, *sim.arena.anchors[seat], 41, 3.5)
            await until(lambda: view.read_corner(slot, seat)[2] == old and
                        P.decode_corner(view.read_corner(slot, seat)[1]).hip_seq == 41, 10,
                        "the former occupant's HIP echoed")
            sent: list[P.Corner] = []
            w.frame_loop.lock()  # no pass until released
            try:
                sim.set_hip(seat, None)  # the seat changes hands
                new = sim.occupant[seat]
                assert new != old
                place = sim.lane_place(seat)
                spec = LaneSpec("r", w.block_id, slot, seat, new, (-9.0,) * 3, (9.0,) * 3,
                                1 / 120, 1000.0, 1000.0, None, place["board_slot"])
                lane = Lane(spec, links, lambda kind, head, msg: sent.append(
                    P.decode_corner(msg)), lambda: "r")
                await asyncio.sleep(0.05)  # its timer looks several times meanwhile
                assert sent == []
            finally:
                w.frame_loop.unlock()
            await until(lambda: len(sent) >= 3, 10, "the new occupant's CORNERs")
            assert all(c.hip_seq == 0 and math.isnan(c.hip_time) for c in sent)
            lane.close()
            links.stop()

    run(main())
