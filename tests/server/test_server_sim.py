"""The room's simulation thread (how it catches up, the catch-up bound) and the MESH fan-out
(every spectator served when it is spread over several passes of the event loop)."""

from __future__ import annotations

import asyncio
import time

from clothball.game.net.client import NetClient
from clothball.game.wire.protocol import decode_mesh
from clothball.server import room as room_mod
from clothball.server.room import RoomSettings
from clothball.server.sim import RoomSim

from tests.server.conftest import TINY, run, server


class ManualClock:
    """A clock that moves only when the test moves it (the thread still sleeps for real)."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def wait_for(cond, what: str, timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.005)


def test_a_backlog_is_stepped_a_quarter_at_a_time_and_the_excess_skipped() -> None:
    clock = ManualClock()
    sim = RoomSim(TINY, "cpu", clock=clock, epoch=0.0, max_catchup=50)
    sim.start()
    try:
        st = sim.stats
        clock.t = 10.5 * sim.frame_dt  # ten frames due at once
        wait_for(lambda: st.frames >= 10, "ten frames")
        # Not one batch: steps of 3, 2, 2, 1, 1, 1 frames, each with the newest HIPs and
        # its own corner state.
        assert (st.frames, st.steps, st.skipped_frames) == (10, 6, 0)
        assert len(st.lateness) == 6
        clock.t = 210.5 * sim.frame_dt  # 200 more due: 50 are simulated, 150 skipped
        wait_for(lambda: st.frames >= 60, "the catch-up")
        time.sleep(0.05)  # nothing more is due: the thread sleeps
        # 50 frames in steps of 13, 10, 7, 6, 4, 3, 2, 2, 1, 1, 1.
        assert (st.frames, st.steps, st.skipped_frames) == (60, 17, 150)
        assert sim.frame == 60
    finally:
        sim.stop()


def test_every_spectator_gets_the_mesh_when_the_fan_out_takes_several_passes(tmp_path) -> None:
    n_spec = 3 * room_mod.MESH_FANOUT_CHUNK + 1

    async def main() -> None:
        async with server(tmp_path, settings=RoomSettings()) as srv:
            room = srv.main_room
            assert room is not None
            frames: list[set[int]] = [set() for _ in range(n_spec)]
            specs = []
            for i in range(n_spec):
                c = await NetClient.connect(srv.ws_url, role="spectator", room=room.id,
                                            decode_mesh=False)
                c.on_mesh = lambda data, s=frames[i]: s.add(decode_mesh(data).frame)
                specs.append(c)
            await asyncio.sleep(2.0)
            for c in specs:
                await c.close()
        assert all(len(f) >= 10 for f in frames), [len(f) for f in frames]
        # The same meshes reached the first and the last chunk of spectators.
        assert len(set.intersection(*frames)) >= 5

    run(main())


def test_lateness_samples_keep_the_newest_in_a_fixed_ring() -> None:
    from clothball.server.sim import Samples

    ring = Samples(5)
    ref: list[float] = []
    for k in range(13):
        ring.append(float(k))
        ref.append(float(k))
        assert len(ring) == min(len(ref), 5)
        assert ring.newest().tolist() == ref[-5:]
        assert ring.newest(2).tolist() == ref[-2:]
        # what came after the first j samples, as far as the ring still holds it
        for j in range(len(ref) + 1):
            assert ring.since(j).tolist() == ref[j:][-5:]
    ring.clear()
    assert len(ring) == 0 and ring.newest().tolist() == [] and ring.since(3).tolist() == []
