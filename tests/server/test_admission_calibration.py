"""Admission's calibration (server/headroom.py) on the CPU backend: with the native frame
loop a room costs what its stepped frames cost of the loop thread's CPU time (frames
skipped, falling behind, not counted), read from the loop itself
(``FrameLoop.cpu_seconds``, checked against the kernel's count for that thread in /proc),
not the Python per-frame call the loop no longer makes."""

from __future__ import annotations

import os
import time

import pytest
from clothball.game.sim.scene import Scene
from clothball.server import headroom
from clothball.server.sim import RoomSim, SimPool
from clothball.server.sim import worker as sim_worker

from tests.server.conftest import TINY

TICK = os.sysconf("SC_CLK_TCK")


def _wait(pred, timeout: float) -> None:
    end = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < end, f"timed out waiting for {pred}"
        time.sleep(0.01)


def _names() -> dict[str, str]:
    """This process's threads, by id, with their names."""
    names = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/comm") as f:
                names[tid] = f.read().strip()
        except FileNotFoundError:  # ended meanwhile
            continue
    return names


def _threads() -> set[str]:
    """This process's threads but the CUDA driver's own (named cuda...: on a GPU machine it
    starts them when the process first looks for a device, and keeps them)."""
    return {tid for tid, name in _names().items() if not name.startswith("cuda")}


def _thread_cpu(tid: int) -> float:
    """The kernel's CPU seconds for thread ``tid`` of this process (utime + stime)."""
    with open(f"/proc/self/task/{tid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="needs Linux /proc")
def test_the_loop_reports_its_own_threads_cpu_time() -> None:
    before = _threads()
    pool = SimPool(cpu_loops=1)
    try:
        sims = [RoomSim(TINY, "cpu", pool=pool) for _ in range(8)]
        for s in sims:
            s.start()
        worker = sims[0].worker
        # The threads the worker started: the frame loop's and its service thread.
        new = sorted(int(t) for t in _threads() - before)
        assert len(new) == 2, new
        (loop_tid,) = [t for t in new if t != worker.service_thread_id]
        _wait(lambda: worker.cpu_seconds() > 0.2, timeout=120)
        ours, kernel = worker.cpu_seconds(), _thread_cpu(loop_tid)
        # Read one after the other: the kernel's count is in clock ticks (10 ms) and may
        # have moved on by a tick or two since.
        assert kernel - 3.0 / TICK <= ours <= kernel + 3.0 / TICK, (ours, kernel)
        # It is a thread's CPU time, not the process's.
        assert ours < time.process_time()
        for s in sims:
            s.stop()
    finally:
        pool.close()


def test_a_cpu_room_costs_the_difference_of_two_native_measures(monkeypatch) -> None:
    """The native loop measured with one room and with CALIBRATE_ROOMS_NATIVE: a room costs
    the difference's share, the thread the rest; ClothBatch's per-frame Python call is not
    timed."""
    monkeypatch.setattr(headroom, "_costs", {})
    calls: list[tuple[str, int]] = []
    many = headroom.CALIBRATE_ROOMS_NATIVE

    def native(scene, backend, rooms):
        calls.append(("native", rooms))
        return 0.05 + 0.3 * rooms  # a thread's own 0.05, 0.3 a room

    def batch(scene, key, rooms):
        calls.append(("batch", rooms))
        return 3.0

    monkeypatch.setattr(headroom, "_native_cost", native)
    monkeypatch.setattr(headroom, "_frame_cost", batch)
    assert headroom.room_cost(TINY, "cpu") == pytest.approx(0.3)
    assert headroom.thread_cost(TINY, "cpu") == pytest.approx(0.05)
    assert calls == [("native", 1), ("native", many)]


def test_a_room_the_loop_cannot_keep_up_with_costs_what_its_frames_cost() -> None:
    """Issue 40: rooms whose frames need more than the loop's one thread (the thread falls
    behind and skips frames). The measure is over the frames it stepped, so it says what
    they would need at real time, as the same rooms timed one ClothBatch call a frame on
    one thread (an independent measure) say, and not the thread's
    one core shared out (which made a default room look 0.06 cores where it costs 0.34)."""
    heavy = Scene.load("classic").with_changes({"cloth": {"n": 128}})
    rooms = headroom.CALIBRATE_ROOMS_NATIVE
    key = headroom._key(heavy, "cpu")
    reference = headroom._frame_cost(heavy, key, rooms)
    if reference <= 1.5:  # pragma: no cover - a machine fast enough to keep up
        pytest.skip(f"{rooms} rooms of n = 128 need only {reference:.2f} cores here")
    measured = headroom._native_cost(heavy, "cpu", rooms)
    assert measured > 1.0  # more than the one core the thread had: not its CPU shared out
    assert 0.5 * reference <= measured <= 2.0 * reference, (measured, reference)


def test_the_native_measure_runs_the_loop_and_gives_a_cost(monkeypatch) -> None:
    """A real calibration: a positive cost, and every thread it started is gone after (the
    pool closed: its frame loop's, its service thread's, its MESH encoders', three of them
    as on a host of 12 cores or more)."""
    monkeypatch.setattr(sim_worker, "MESH_THREADS", 3)
    threads = _threads() if os.path.isdir("/proc/self/task") else None
    assert headroom._native_cost(TINY, "cpu", 4) > 0.0
    if threads is not None:
        end = time.monotonic() + 10
        while not _threads() <= threads and time.monotonic() < end:
            time.sleep(0.01)
        names = _names()
        assert {t: names.get(t) for t in _threads() - threads} == {}


def test_a_cpu_scene_spread_over_two_loops_is_admitted_per_loop(monkeypatch) -> None:
    """The cost model follows SimPool.worker_for: on the CPU engine a scene's rooms go to
    ``cpu_loops`` threads by turns, so a thread's limit is met at that many times the rooms,
    and each thread's fixed cost counts once. A thread's own 0.05 core and 0.3 a room, 75 %
    of a thread and of 4 cores: one loop takes 2 rooms (0.05 + 3 x 0.3 > 0.75 for a third);
    two take 4 (the fifth would be a third on one thread)."""
    key = headroom._key(TINY, "cpu")
    monkeypatch.setattr(headroom, "_costs", {key: (0.05, 0.3)})

    class Pool:
        workers: list = []

        def __init__(self, loops: int) -> None:
            self.cpu_loops = loops

        def capacity_for(self, backend: str) -> int:
            return 64

    def admitted(loops: int) -> int:
        hr = headroom.Headroom(Pool(loops), 0.0, load=0.75, cores=4.0,  # type: ignore[arg-type]
                               backend="cpu")
        rooms: list[Scene] = []
        while hr.refusal(TINY, rooms) is None and len(rooms) < 20:
            rooms.append(TINY)
        return len(rooms)

    assert admitted(1) == 2
    assert admitted(2) == 4
    hr = headroom.Headroom(Pool(2), 0.0, load=0.75, cores=4.0, backend="cpu")  # type: ignore[arg-type]
    assert "its simulation thread steps 2 such rooms" in hr.refusal(TINY, [TINY] * 4)


def test_a_cuda_scene_counts_a_fixed_cost_for_each_worker(monkeypatch) -> None:
    """On the CUDA engine a scene's rooms fill workers of ``capacity_for("cuda")`` rooms, a
    thread (and a launch) each, so the fixed cost counts once a worker. A worker's 0.5 core
    and 0.01 a room, workers of 2 rooms, 2 cores: six rooms need 3 x 0.5 + 0.06 = 1.56, a
    seventh a fourth worker (2.07 > 2). (The arithmetic only: no GPU needed.)"""
    monkeypatch.setattr(headroom, "resolve_backend", lambda s, b, p: ("cuda", "float32", None))
    key = headroom._key(TINY, "cuda")
    monkeypatch.setattr(headroom, "_costs", {key: (0.5, 0.01)})

    class Pool:
        workers: list = []

        def capacity_for(self, backend: str) -> int:
            return 2 if backend == "cuda" else 64

    hr = headroom.Headroom(Pool(), 0.0, load=1.0, cores=2.0,  # type: ignore[arg-type]
                           backend="cuda")
    rooms: list[Scene] = []
    while hr.refusal(TINY, rooms) is None and len(rooms) < 20:
        rooms.append(TINY)
    assert len(rooms) == 6
    # (the fourth worker's fixed cost counted with them, as the seventh room would start it)
    assert "its 6 rooms need about 2.06 of the 2.00 cores" in hr.refusal(TINY, rooms)
