"""The native frame loop (native/loop, server/sim/worker.py; docs/worker.md): its exit
check against ``game.rules.exit_edge``, its block's layout as the binding exports it, its
rooms stepped and published without Python, its meshes (one gather of the due rooms'
nodes) against the batch's own, a stalled event loop that loses nothing, and a loop that
is behind which still lets rooms in and out."""

from __future__ import annotations

import asyncio
import math
import os
import select
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from clothball import _native
from clothball.game.rules import exit_edge
from clothball.game.sim.cloth import corners_of, rest_positions
from clothball.game.wire import protocol as P
from clothball.server.sim import RoomSim, SimPool
from clothball.server.sim import worker as sim_worker

from tests.server.conftest import TINY, run, started_room, until


def _random_states(rng: np.random.Generator, count: int):
    """Corner quadrilaterals around the rest square (some nearly degenerate), and balls
    anywhere over and around them: on the cloth, just inside and just outside an edge's
    line (1e-9 .. 1e-3 m), at an edge's height, at the floor, far off."""
    rest = corners_of(rest_positions(TINY))
    size = float(TINY["cloth"]["size"])
    floor_y = float(TINY["cloth"]["height"]) - 1.5 * size
    for k in range(count):
        corners = rest + rng.normal(0.0, 0.1 * size, (4, 3))
        if k % 17 == 0:  # two corners nearly on one another: an edge of ~zero length
            corners[1] = corners[0] + rng.normal(0.0, 1e-13, 3)
        kind = k % 5
        if kind == 0:  # anywhere around
            ball = np.array([rng.uniform(-1.5, 1.5) * size, rng.uniform(floor_y - 0.2, 1.0),
                             rng.uniform(-1.5, 1.5) * size])
        else:  # near an edge's line: inside or outside by a small amount
            e = int(rng.integers(4))
            a, b = corners[e], corners[(e + 1) % 4]
            t = rng.uniform(-0.1, 1.1)
            p = a + t * (b - a)
            centre = corners.mean(axis=0)
            out = p - centre
            out[1] = 0.0
            out /= max(np.linalg.norm(out), 1e-12)
            p = p + out * rng.choice([-1.0, 1.0]) * 10.0 ** rng.uniform(-9, -3)
            height = p[1]
            if kind == 1:
                p[1] = height + rng.choice([-1.0, 1.0]) * 10.0 ** rng.uniform(-9, -2)
            elif kind == 2:
                p[1] = floor_y + rng.choice([-1.0, 1.0, 0.0]) * 10.0 ** rng.uniform(-9, -2)
            else:
                p[1] = rng.uniform(floor_y - 0.1, height + 0.1)
            ball = p
        yield ball, corners, floor_y


def test_the_native_exit_check_gives_exit_edges_answer_over_random_states() -> None:
    rng = np.random.default_rng(32)
    counts = {e: 0 for e in (-1, 0, 1, 2, 3)}
    for ball, corners, floor_y in _random_states(rng, 5000):
        want = exit_edge(ball, corners, floor_y)
        got = _native.exit_edge(ball, corners, floor_y)
        assert got == (-1 if want is None else want), (ball.tolist(), corners.tolist(), floor_y)
        counts[got] += 1
    # every answer was exercised, in play and each edge
    assert all(n > 100 for n in counts.values()), counts


def test_cpu_rooms_are_spread_over_the_loops_asked_for(monkeypatch) -> None:
    """``CLOTHBALL_CPU_LOOPS=2``: the CPU engine's rooms of one scene go to two frame loops
    by turns (the one with fewer rooms), not all to the first; a bad value is refused
    saying what to give."""
    monkeypatch.setenv("CLOTHBALL_CPU_LOOPS", "2")
    pool = SimPool()
    sims = [RoomSim(TINY, "cpu", pool=pool) for _ in range(5)]
    try:
        workers = pool.workers
        assert len(workers) == 2
        assert sorted(w.members for w in workers) == [2, 3]
        assert {id(s.worker) for s in sims} == {id(w) for w in workers}
    finally:
        for s in sims:
            s.stop()
        pool.close()
    monkeypatch.setenv("CLOTHBALL_CPU_LOOPS", "0")
    with pytest.raises(ValueError, match="CLOTHBALL_CPU_LOOPS='0': give a whole number"):
        SimPool()
    monkeypatch.delenv("CLOTHBALL_CPU_LOOPS")
    # the rooms a loop steps (a worker's batch), for A/B runs; checked the same way
    assert (SimPool().capacity_for("cuda"), SimPool().capacity_for("cpu")) == (256, 64)
    monkeypatch.setenv("CLOTHBALL_LOOP_ROOMS", "3")
    assert (SimPool().capacity_for("cuda"), SimPool().capacity_for("cpu")) == (3, 3)
    assert SimPool(capacity=5).capacity_for("cuda") == 5
    monkeypatch.setenv("CLOTHBALL_LOOP_ROOMS", "2000")
    with pytest.raises(ValueError, match="CLOTHBALL_LOOP_ROOMS='2000': give a whole number"):
        SimPool()


def test_the_block_layout_is_the_bindings_and_the_block_says_so() -> None:
    layout = sim_worker.LAYOUT
    assert sim_worker.ROOM_DTYPE.itemsize == layout["room_bytes"]
    assert sim_worker.ROOM_DTYPE.fields["hip_pos"][0].shape == (4, 3)
    assert sim_worker.ENGINE_DTYPE.fields["lateness"][0].shape == (layout["lateness_ring"],)
    pool = SimPool()
    sample = RoomSim(TINY, "cpu", pool=pool)
    try:
        w = sample.worker
        assert isinstance(w, sim_worker.FrameWorker)
        head = np.frombuffer(w.frame_loop.block(), dtype=np.uint8)
        magic = int(head[:8].view(np.uint64)[0])
        version = int(head[8:12].view(np.uint32)[0])
        assert (magic, version) == (layout["magic"], layout["version"])
        assert b"CLOTBLK1" == head[:8].tobytes()
        total = len(head)
        assert total == layout["header_bytes"] + w.batch.capacity * layout["room_bytes"] + \
            layout["engine_bytes"]
    finally:
        sample.stop()
        pool.close()


def test_rooms_step_on_the_native_loop_and_publish_corners_forces_and_ball(backend: str) -> None:
    """On each backend (CUDA: the batch's graph a frame and its gather copy for meshes)."""
    async def main() -> None:
        got: list = []
        meshes: list[bytes] = []
        pool = SimPool()
        sim = RoomSim(TINY, backend, pool=pool, deliver=got.append, deliver_mesh=meshes.append)
        try:
            assert sim.backend == backend
            sim.start()
            hand = sim.arena.anchors[1] + np.array([0.0, 0.05, 0.0])
            sim.set_hip(1, hand, 7, 12.5)
            await until(lambda: sim.frame > 200, 10, "frames")
            await until(lambda: any(r.corners for r in got), 5, "a delivery")
            r = [r for r in got if r.corners][-1]
            c = P.decode_corner(r.corners[1])
            assert c.hip_seq == 7 and c.hip_time == 12.5  # the HIP applied, echoed
            # -K (h - c), from the corner the message reports
            assert np.allclose(c.force, -sim.arena.stiffness * (hand - c.position), atol=1e-3)
            c0 = P.decode_corner(r.corners[0])
            assert c0.hip_seq == 0 and math.isnan(c0.hip_time)
            assert sim.stats.steps > 0 and sim.stats.skipped_frames >= 0
            assert len(sim.worker.lateness) > 0 and len(sim.stats.lateness) > 0
            # asleep: the frames stop; awake: they go on
            sim.set_awake(False)
            # The loop's lock, taken and given back: a pass that read the room awake has
            # ended (a pass holds the lock throughout; the next reads it asleep), however
            # slowly it ran, instead of a fixed 50 ms for it.
            sim.worker.frame_loop.lock()
            sim.worker.frame_loop.unlock()
            f = sim.frame
            await asyncio.sleep(0.1)  # (a fixed wait on purpose: no frame in it)
            assert sim.frame == f
            sim.set_awake(True)
            await until(lambda: sim.frame > f + 50, 10, "awake again")
            await until(lambda: bool(meshes), 10, "a mesh")
            mesh = P.decode_mesh(meshes[-1])
            assert mesh.positions.shape == (TINY.n, TINY.n, 3)
            assert np.all(np.isfinite(mesh.positions)) and sim.stats.meshes > 0
            # A round's ball reset (one native call, the loop's lock taken without the GIL):
            # the ball is where it was put, at rest high above the cloth, and then falls
            # freely (at most g t^2 / 2 in the frames since, x and z unchanged).
            f0 = sim.frame
            sim.command("reset_ball", (np.array([0.3, 2.0, -0.2]), np.zeros(3)))
            await until(lambda: any(r.corners and r.frame > f0 + 20 for r in got), 10,
                        "frames after the reset")
            c = P.decode_corner([r for r in got if r.corners][-1].corners[0])
            t = (c.frame - f0 + 1) * TINY["sim"]["frame_dt"]
            assert c.ball_position[0] == pytest.approx(0.3, abs=1e-5)
            assert c.ball_position[2] == pytest.approx(-0.2, abs=1e-5)
            assert 2.0 - 0.5 * 9.81 * t * t - 1e-4 < c.ball_position[1] < 2.0
            assert c.ball_velocity[1] < 0
            with pytest.raises(ValueError, match="finite"):
                sim.worker.set_ball(sim.slot, np.array([0.0, np.nan, 0.0]), np.zeros(3))
        finally:
            sim.stop()
            pool.close()

    run(main())


def test_meshes_come_from_the_loop_for_every_room_at_its_rate() -> None:
    """Each room's MESH, made from the loop's one gather of the due rooms' nodes (checked
    against each slot's own positions in tests/engine/test_batch_gather.py), arrives for
    every room, newest frame first, decodable."""
    async def main() -> None:
        pool = SimPool()
        got: dict[int, list] = {0: [], 1: []}
        sims = [RoomSim(TINY, "cpu", pool=pool, deliver_mesh=got[k].append) for k in range(2)]
        try:
            for s in sims:
                s.start()
            await until(lambda: all(len(m) >= 3 for m in got.values()), 10,
                        "meshes of both rooms")
            for k, s in enumerate(sims):
                meshes = [P.decode_mesh(m) for m in got[k]]
                frames = [m.frame for m in meshes]
                assert frames == sorted(frames) and len(set(frames)) == len(frames)
                assert all(m.positions.shape == (TINY.n, TINY.n, 3) for m in meshes)
                assert s.stats.meshes >= len(meshes)
        finally:
            for s in sims:
                s.stop()
            pool.close()

    run(main())


def test_a_stalled_event_loop_loses_no_frames_and_gets_the_newest_late() -> None:
    """The event loop blocks 200 ms: the native loop keeps pace (frames advance, none
    skipped); the stall shows as one late delivery of the newest frame, and an exit found
    during it is delivered after it, not lost."""
    async def stall() -> None:
        pool = SimPool()
        got: list = []
        sim = RoomSim(TINY, "cpu", pool=pool, deliver=got.append)
        try:
            sim.start()
            await until(lambda: sim.frame > 100, 10, "frames")
            skipped0 = sim.stats.skipped_frames
            f0 = sim.frame
            delivered0 = max(r.frame for r in got if r.corners)
            # a ball below the floor and far off the cloth, armed: it exits at once, while
            # the event loop is stalled
            off = np.array([10.0 * sim.arena.size, sim.arena.floor_y - 1.0, 0.0])
            sim.command("reset_ball", (off, np.zeros(3)))
            sim.command("arm")
            # The event loop is blocked (no delivery can happen) until ~200 frames went by:
            # counted, not a fixed 0.2 s (fewer fit in it on a loaded machine).
            end = time.monotonic() + 30
            while sim.frame < f0 + 200 and time.monotonic() < end:
                time.sleep(0.005)
            f1 = sim.frame
            assert max(r.frame for r in got if r.corners) == delivered0  # nothing delivered
            assert not any(r.exit for r in got)
            await asyncio.sleep(0)  # the loop runs again: the newest frame arrives
            await until(lambda: max(r.frame for r in got if r.corners) >= f1, 5, "delivery")
            # the exit found during the stall is delivered after it, with its own frame
            exits = [r.exit for r in got if r.exit]
            assert len(exits) == 1
            edge, frame, ball = exits[0]
            assert delivered0 < frame < f1 and edge in range(4) and ball[1] < sim.arena.floor_y
            # ~200 frames went by during the stall, none dropped
            assert f1 - f0 >= 200, (f0, f1)
            assert sim.stats.skipped_frames == skipped0
            assert sim.worker.skipped_frames == 0
        finally:
            sim.stop()
            pool.close()

    run(stall())



def test_a_loop_that_cannot_keep_up_still_lets_rooms_in_and_out_and_stops() -> None:
    """Rooms too large for 1 kHz here keep the loop behind, pass after pass with no sleep
    between (catching up); adding a room, removing one and stopping the loop, which wait
    for its lock from the event loop's thread, still happen (they waited forever when the
    loop kept its lock from one pass to the next). In a process of its own, so that a
    hang fails the test (by the timeout, a bound on a hang, not a speed claim) instead of
    hanging the suite."""
    script = textwrap.dedent("""
        import asyncio, time
        from clothball.game.sim.scene import Scene
        from clothball.server.sim import RoomSim, SimPool

        async def main():
            big = Scene.load("default").with_changes({"cloth": {"n": 128}})
            pool = SimPool(cpu_loops=1)  # (else the rooms go to a loop each, on many cores)
            sims = [RoomSim(big, "cpu", pool=pool) for _ in range(3)]
            for s in sims:
                s.start()
            await asyncio.sleep(0.5)  # (the rooms under way: a fixed wait, nothing asserted)
            f0 = sims[0].frame
            await asyncio.sleep(0.5)  # (a fixed window for an upper bound: load only lowers it)
            assert sims[0].frame - f0 < 450, ("1 kHz kept: not a test of a loop behind",
                                              sims[0].frame - f0)
            extra = RoomSim(big, "cpu", pool=pool)
            extra.start()  # waits for the loop's lock
            extra.stop()   # and again
            for s in sims:
                s.stop()
            pool.close()   # stops the loop
            print("ok")

        asyncio.run(main())
    """)
    # The machine's cores for the loop, one thread: the rooms are behind wherever this
    # runs (n = 128, the default scene's substeps: milliseconds a frame a room on one core;
    # at n = 64 the vectorised CPU sweep came within 1 % of 1 kHz on a 2-core VM).
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=60, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stdout + out.stderr


def test_a_gateways_view_of_the_block_writes_hands_of_the_seats_occupant_only() -> None:
    """Another process's view of the block (``_native.BlockView`` over the memfd mapped
    anew, as a gateway maps it: server.shared.lanes): a hand written for the seat's
    occupant is applied and echoed, and its CORNER read there is the one the loop
    published; a hand for an occupant that has left is refused, and one that lands anyway
    (written as the seat changed hands) is ignored by the loop."""
    import mmap

    async def main() -> None:
        with started_room() as sim:
            place = sim.lane_place(2)
            slot, occupant = place["slot"], place["occupant"]
            _, fd, size = sim.worker.block_share
            assert place["block"] == sim.worker.block_id
            with open(f"/proc/self/fd/{fd}", "r+b") as f:
                view = _native.BlockView(mmap.mmap(f.fileno(), size))
            assert view.rooms >= 1
            hand = sim.arena.anchors[2] + np.array([0.02, 0.04, 0.0])
            assert view.write_hip(slot, 2, occupant, *hand, 41, 3.5)
            await until(lambda: view.read_corner(slot, 2)[0] > 100, 10, "frames")

            def corner() -> P.Corner:
                return P.decode_corner(view.read_corner(slot, 2)[1])

            await until(lambda: corner().hip_seq == 41, 5, "the hand applied")
            c = corner()
            assert c.hip_time == 3.5 and c.seat == 2
            assert np.allclose(c.force, -sim.arena.stiffness * (hand - c.position), atol=1e-3)
            frame, raw, occ = view.read_corner(slot, 2)
            assert occ == occupant
            assert raw[:1] == bytes([P.CORNER]) and P.decode_corner(raw).frame == frame
            # The seat changes hands: the old occupant's hand is refused, the corner rests.
            sim.set_hip(2, None)
            assert not view.write_hip(slot, 2, occupant, *hand, 42, 4.0)
            rec = sim.worker.rooms_view
            # ... and one written as the seat changed hands (the old occupant's, has set)
            # is not applied.
            rec["hip_occupant"][slot, 2] = occupant
            rec["hip_has"][slot, 2] = 1
            f0 = view.read_corner(slot, 2)[0]
            await until(lambda: view.read_corner(slot, 2)[0] > f0 + 5, 5, "frames")
            c = corner()
            assert c.hip_seq == 0 and math.isnan(c.hip_time)
            # the new occupant's is
            occupant2 = sim.lane_place(2)["occupant"]
            assert occupant2 != occupant
            assert view.write_hip(slot, 2, occupant2, *hand, 1, 9.0)
            await until(lambda: corner().hip_seq == 1, 5, "the new occupant's hand")
            with pytest.raises(IndexError):
                view.write_hip(view.rooms, 0, occupant2, 0.0, 0.0, 0.0, 1, 0.0)
            with pytest.raises(ValueError, match="not a frame loop block"):
                _native.BlockView(bytearray(4096))

    run(main())


def test_a_wake_up_is_written_after_each_pass_until_it_is_removed() -> None:
    """A gateway's frame wake-up (``SimPool.set_wake``): an eventfd every native frame loop
    writes once a pass while it is set, one at a time for each pass (the count it reads is
    the passes since its last read, at most the frames the room advanced), and never once
    it is removed (a loop created meanwhile has it too)."""
    async def main() -> None:
        fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        try:
            with started_room() as sim:
                pool, view, slot = sim.pool, sim.worker.rooms_view, sim.slot
                await until(lambda: int(view["frame"][slot]) > 10, 10, "frames")
                pool.set_wake(fd, True)
                f0 = int(view["frame"][slot])
                with pytest.raises(BlockingIOError):  # drained (a pass may write meanwhile)
                    while True:
                        os.eventfd_read(fd)
                # a pass's wake-up written since (waited for, not a fixed 0.1 s)
                await until(lambda: bool(select.select([fd], [], [], 0)[0]), 10, "a wake-up")
                n = os.eventfd_read(fd)
                f1 = int(view["frame"][slot])
                # (+1: a pass that published before f0 was read may write it after the drain)
                assert 0 < n <= f1 - f0 + 1, (n, f0, f1)
                pool.set_wake(fd, False)
                with pytest.raises(BlockingIOError):
                    while True:
                        os.eventfd_read(fd)
                await until(lambda: int(view["frame"][slot]) > f1 + 20, 5, "frames")
                with pytest.raises(BlockingIOError):
                    os.eventfd_read(fd)
            # Set before any loop is made: the loop made for a room then writes it too.
            pool = SimPool()
            pool.set_wake(fd, True)
            with started_room(pool=pool) as sim:
                await until(lambda: int(sim.worker.rooms_view["frame"][sim.slot]) > 10, 10,
                            "frames")
                assert os.eventfd_read(fd) > 0
                pool.set_wake(fd, False)
            pool.close()
        finally:
            os.close(fd)

    run(main())
