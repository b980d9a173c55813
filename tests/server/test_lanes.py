"""The lane code (server/lanes/lane.py) that serves every seated player's HIPs and CORNERs
and every client's MESH, in the engine and in a gateway alike: a CORNER made from a former
occupant's hand is never sent to the seat's new occupant, whatever the timing; CORNER timers
fire on a grid of whole frames, so that lanes due within one frame share a wake-up."""

from __future__ import annotations

import asyncio
import math

from clothball.game.wire import protocol as P
from clothball.server.lanes.lane import FRAME_S, Lane, on_grid
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


def test_on_grid_rounds_up_to_a_whole_frame() -> None:
    for t in (0.0, 0.0004, 0.001, 1234.5678901, 98765.4321):
        g = on_grid(t)
        assert t - 1e-9 <= g < t + FRAME_S
        assert abs(g / FRAME_S - round(g / FRAME_S)) < 1e-6
        assert on_grid(g) == g


def test_corner_timers_fire_on_the_frame_grid() -> None:
    """Four seats' lanes at corner_rate 120, opened at different moments: every CORNER
    timer they set (a retry, looking again for a frame not yet there, aside) is due at a
    whole frame of the loop's clock, so lanes due within the same frame wake the loop once."""
    async def main() -> None:
        with started_room() as sim:
            w = sim.worker
            links = LocalLinks(sim.pool.local_shares, sim.pool.set_wake)
            loop = asyncio.get_running_loop()
            whens: list[float] = []
            sent = [0] * 4
            call_at = loop.call_at

            def spy(when: float, callback, *args, **kw):  # type: ignore[no-untyped-def]
                owner = getattr(callback, "__self__", None)
                if isinstance(owner, Lane) and owner._retries == 0:
                    whens.append(when)
                return call_at(when, callback, *args, **kw)

            loop.call_at = spy  # type: ignore[method-assign]
            lanes = []
            try:
                place = sim.lane_place(0)
                for seat in range(4):
                    spec = LaneSpec("r", w.block_id, sim.slot, seat, sim.occupant[seat],
                                    (-9.0,) * 3, (9.0,) * 3, 1 / 120, 1000.0, 1000.0, None,
                                    place["board_slot"])

                    def count(kind: str, head: bytes, msg: bytes, seat: int = seat) -> None:
                        sent[seat] += 1

                    lanes.append(Lane(spec, links, count, lambda: "r"))
                    await asyncio.sleep(0.0003 * (seat + 1))
                await until(lambda: min(sent) >= 5, 10, "five CORNERs a lane")
            finally:
                loop.call_at = call_at  # type: ignore[method-assign]
                for lane in lanes:
                    lane.close()
                links.stop()
            assert len(whens) >= 16
            off = [abs(t / FRAME_S - round(t / FRAME_S)) for t in whens]
            assert max(off) < 1e-6, off

    run(main())
