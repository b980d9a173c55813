"""The room's frame loop (how it catches up, the catch-up bound, under a test's clock set
natively: ``SimPool(manual_clock=True)``), wind gusts stepped by the loop as a lone cloth
steps them, and the MESH fan-out (every spectator served, the same meshes)."""

from __future__ import annotations

import time

import numpy as np
from clothball.game.net.client import NetClient
from clothball.game.sim.cloth import Cloth
from clothball.game.sim.scene import Scene
from clothball.game.wire.protocol import decode_mesh
from clothball.server.room import RoomSettings
from clothball.server.sim import RoomSim, SimPool

from tests.server.conftest import TINY, run, server, until


def wait_for(cond, what: str, timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.005)


def test_a_backlog_is_stepped_a_quarter_at_a_time_and_the_excess_skipped() -> None:
    pool = SimPool(manual_clock=True, max_catchup=50)
    sim = RoomSim(TINY, "cpu", pool=pool)
    sim.start()
    try:
        st = sim.stats
        pool.set_clock(10.5 * sim.frame_dt)  # ten frames due at once
        wait_for(lambda: st.frames >= 10, "ten frames")
        # Not one batch: steps of 3, 2, 2, 1, 1, 1 frames, each with the newest HIPs and
        # its own corner state.
        assert (st.frames, st.steps, st.skipped_frames) == (10, 6, 0)
        assert len(st.lateness) == 6
        pool.set_clock(210.5 * sim.frame_dt)  # 200 more due: 50 are simulated, 150 skipped
        wait_for(lambda: st.frames >= 60, "the catch-up")
        time.sleep(0.05)  # nothing more is due: the thread sleeps
        # 50 frames in steps of 13, 10, 7, 6, 4, 3, 2, 2, 1, 1, 1.
        assert (st.frames, st.steps, st.skipped_frames) == (60, 17, 150)
        assert sim.frame == 60
        assert sim.now() == 210.5 * sim.frame_dt
    finally:
        sim.stop()
        pool.close()


def test_wind_gusts_are_blown_by_the_loop_as_a_lone_cloth_blows_them() -> None:
    """The windy scene's gusts (the wind changes every frame) on the native loop, under a
    test's clock, a frame a pass: after the same frames, with the hands at their anchors,
    the room's cloth is the lone ``Cloth``'s (CPU, one thread, the same frames), bit for
    bit, and not the cloth a steady wind blows."""
    windy = Scene.load("windy").with_changes({"cloth": {"n": 12}})
    assert windy["wind"]["gust_amplitude"] > 0
    got: list = []
    pool = SimPool(manual_clock=True, max_catchup=400)
    sim = RoomSim(windy, "cpu", pool=pool, deliver=got.append)
    frames = 300
    try:
        sim.start()
        dt = sim.frame_dt
        for k in range(1, frames + 1):  # a frame a pass: each the newest hands'
            pool.set_clock((k + 0.5) * dt)
            wait_for(lambda k=k: sim.frame >= k, f"frame {k}")
        nodes = sim.worker.batch.positions(sim.slot)
    finally:
        sim.stop()
        pool.close()
    lone = Cloth(windy, backend="cpu", threads=1)
    lone.step(frames)
    np.testing.assert_array_equal(nodes, lone.positions())
    still = Cloth(windy.with_changes({"wind": {"gust_amplitude": 0.0}}), backend="cpu",
                  threads=1)
    still.step(frames)
    assert np.abs(still.positions() - nodes).max() > 1e-4


def test_every_spectator_gets_the_same_meshes(tmp_path) -> None:
    """25 spectators of one room: each gets the room's MESH at its rate, the same frames
    (their lanes send each newer MESH from the room's board on one look for all of them:
    server.lanes)."""
    n_spec = 25

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
            try:  # (waited for, not counted in a fixed window: a loaded machine is slower)
                await until(lambda: all(len(f) >= 10 for f in frames)
                            and len(set.intersection(*frames)) >= 5, 30,
                            "ten meshes for every spectator, five of them the same")
            finally:
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
