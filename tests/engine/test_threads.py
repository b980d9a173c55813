"""The CPU engine's thread count (issue 40): chosen by a frame's work and the cores free
now, so that it never runs more threads than there are cores to run them; as asked where
asked; its OpenMP threads sleep rather than spin between parallel regions."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from clothball.game import Cloth, ClothBatch, Scene
from clothball.game.sim import threads

# the busy loops (each seen running first) have been running this long before the machine is
# looked at: a fixed wait on purpose, a loaded machine only makes it longer
SETTLE_S = 0.3


@contextmanager
def busy_loops(k: int) -> Iterator[None]:
    """``k`` processes that spin (two busy loops beside the engine: the issue's case)."""
    procs: list[subprocess.Popen[str]] = []
    try:
        for _ in range(k):
            procs.append(subprocess.Popen(
                [sys.executable, "-c", "print(flush=True)\nwhile True: pass"],
                stdout=subprocess.PIPE, text=True))
        for p in procs:  # each one spinning (its line out: however slowly Python started)
            assert p.stdout is not None and p.stdout.readline() == "\n"
        time.sleep(SETTLE_S)
        threads._free = None  # a fresh look, not one from before the loops
        threads._last = None
        yield
    finally:  # every one started killed, reaped and its pipe closed, whatever happened
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()
            if p.stdout is not None:
                p.stdout.close()


def big_scene() -> Scene:
    """A cloth whose frame is worth two threads by its work (twice MIN_NODES_PER_THREAD)."""
    n = int((2 * threads.MIN_NODES_PER_THREAD) ** 0.5) + 1
    return Scene.load("classic").with_changes({"cloth": {"n": n}})


def test_a_small_cloth_runs_one_thread_and_an_asked_count_is_kept() -> None:
    small = Scene.load("classic").with_changes({"cloth": {"n": 25}})
    assert Cloth(small, backend="cpu").threads == 1  # its barriers would cost more
    assert Cloth(small, backend="cpu", threads=2).threads == 2
    assert ClothBatch(small, 4, backend="cpu", threads=3).threads == 3
    assert threads.choose(10**9, 5) == 5


@pytest.mark.skipif(not os.path.exists("/proc/stat"), reason="needs Linux /proc/stat")
def test_with_every_core_busy_a_large_cloth_runs_one_thread() -> None:
    """Beside a busy loop per core, the free cores are seen as fewer than the cores, and a
    cloth (or batch) worth several threads by its work gets one: a thread waiting for a
    core at each barrier held the others up (12 500 us a substep where one took 17.5)."""
    cores = threads.usable_cores()
    with busy_loops(cores):
        assert threads.free_cores() < cores - 0.5
        assert Cloth(big_scene(), backend="cpu").threads == 1
        scene = Scene.load("classic").with_changes({"cloth": {"n": 16}})
        assert ClothBatch(scene, 4 * threads.MIN_NODES_PER_THREAD // 256,
                          backend="cpu").threads == 1
    note = threads.busy_note()
    assert note is None or "busy" in note


def test_openmp_threads_sleep_between_regions_unless_told_otherwise() -> None:
    code = "import os, clothball.game; print(os.environ.get('OMP_WAIT_POLICY'))"
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=env, timeout=60, check=True)
    assert r.stdout.strip() == "PASSIVE"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env={**env, "OMP_WAIT_POLICY": "ACTIVE"}, timeout=60, check=True)
    assert r.stdout.strip() == "ACTIVE"
