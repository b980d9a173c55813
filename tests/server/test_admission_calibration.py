"""Admission's calibration (server/headroom.py) on the CPU backend: with the native frame
loop a room costs its share of the loop thread's CPU time, read from the loop itself
(``FrameLoop.cpu_seconds``, checked against the kernel's count for that thread in /proc),
not the Python per-frame call the loop no longer makes."""

from __future__ import annotations

import os
import time

import pytest
from clothball.server import headroom
from clothball.server.sim import RoomSim, SimPool

from tests.server.conftest import TINY

TICK = os.sysconf("SC_CLK_TCK")


def _wait(pred, timeout: float) -> None:
    end = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < end, f"timed out waiting for {pred}"
        time.sleep(0.01)


def _thread_cpu(tid: int) -> float:
    """The kernel's CPU seconds for thread ``tid`` of this process (utime + stime)."""
    with open(f"/proc/self/task/{tid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="needs Linux /proc")
def test_the_loop_reports_its_own_threads_cpu_time() -> None:
    before = set(os.listdir("/proc/self/task"))
    pool = SimPool()
    try:
        sims = [RoomSim(TINY, "cpu", pool=pool) for _ in range(8)]
        for s in sims:
            s.start()
        worker = sims[0].worker
        # The threads the worker started: the frame loop's and its service thread.
        new = sorted(int(t) for t in set(os.listdir("/proc/self/task")) - before)
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


def test_a_cpu_room_costs_its_share_of_the_native_loops_cpu(monkeypatch) -> None:
    """The native loop's measure is the room cost (its 16 rooms' share); ClothBatch's
    per-frame Python call is not timed."""
    monkeypatch.setattr(headroom, "_costs", {})
    calls: list[tuple[str, int]] = []

    def native(scene, backend, rooms):
        calls.append(("native", rooms))
        return 0.48

    def batch(scene, key, rooms):
        calls.append(("batch", rooms))
        return 3.0

    monkeypatch.setattr(headroom, "_native_cost", native)
    monkeypatch.setattr(headroom, "_frame_cost", batch)
    assert headroom.room_cost(TINY, "cpu") == pytest.approx(0.48 / 16)
    assert calls == [("native", headroom.CALIBRATE_ROOMS_NATIVE)]


def test_the_native_measure_runs_the_loop_and_gives_a_cost() -> None:
    """A real calibration: a positive cost, under the one core a loop thread can use, and
    every room it started is gone after (the pool closed)."""
    threads = set(os.listdir("/proc/self/task")) if os.path.isdir("/proc/self/task") else None
    cores = headroom._native_cost(TINY, "cpu", 4)
    assert 0.0 < cores <= 1.05
    if threads is not None:
        _wait(lambda: set(os.listdir("/proc/self/task")) <= threads, timeout=10)
