"""The server's sim workers (``SimPool``): one per (scene, backend, precision, mesh and track
pacing), each a native frame loop stepping up to ``capacity`` rooms in one call a frame;
another opens when one is full."""

from __future__ import annotations

import asyncio
import json
import os
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from ...game.sim.cloth import resolve_backend
from ...game.sim.scene import Scene
from ...game.sim.threads import usable_cores
from .worker import FrameWorker, LoopSettings

# Rooms one worker's batch holds; a pool opens another worker of the same scene beyond it.
# On the GPU one launch a frame steps a worker's rooms: 64 rooms fill well under half an
# H200 (a batched frame of 264 default rooms took 171 µs,
# docs/benchmarks/gpu-h200-2026-11-28-roofline/), and a host of 384 rooms on workers of 256
# (two launches a frame, not six) took 4.9 server cores where workers of 64 took 6.1, and
# kept every rate, MESH and the pages too (docs/benchmarks/host-2026-11-28-pump.md, call
# 11). On the CPU a loop holds a few rooms at most. CLOTHBALL_LOOP_ROOMS (1-1024) sets it
# for both, for A/B runs.
WORKER_CAPACITY = 64
CUDA_WORKER_CAPACITY = 256
LOOP_ROOMS_ENV = "CLOTHBALL_LOOP_ROOMS"


def _whole_env(name: str, default: int, most: int) -> int:
    """The environment's ``name``, a whole number from 1 to ``most``, else ``default``.
    Raises ``ValueError`` saying what is wrong."""
    text = os.environ.get(name, "").strip()
    if not text:
        return default
    if not text.isdigit() or not 1 <= int(text) <= most:
        raise ValueError(f"{name}={text!r}: give a whole number from 1 to {most}")
    return int(text)


def loop_rooms_default(backend: str = "cpu") -> int:
    """``LOOP_ROOMS_ENV`` (1-1024), else ``CUDA_WORKER_CAPACITY`` for the CUDA engine and
    ``WORKER_CAPACITY`` for the CPU's."""
    return _whole_env(LOOP_ROOMS_ENV,
                      CUDA_WORKER_CAPACITY if backend == "cuda" else WORKER_CAPACITY, 1024)


# The CPU engine's rooms of one scene are spread over up to this many workers, each a frame
# loop on a thread of its own (one core's stepping each): by default one per core this
# process may use. The CUDA engine's share one worker up to CUDA_WORKER_CAPACITY, one
# launch a frame for all of them. Measured on two pinned cores of the H200 machine (one
# process, default scene n = 16; docs/benchmarks/host-2026-11-28-pump.md, call 10): one
# loop held 4, 2, 4 rooms, two loops 4, 10, 12.
CPU_LOOPS_ENV = "CLOTHBALL_CPU_LOOPS"


def cpu_loops_default() -> int:
    """``CPU_LOOPS_ENV`` (1-64), else the cores this process may use."""
    return _whole_env(CPU_LOOPS_ENV, max(1, min(64, usable_cores())), 64)


class SimPool:
    """The server's sim workers (see the module doc). ``manual_clock``: the loops' time is
    what ``set_clock`` last said (a test's clock, from 0), not the monotonic clock."""

    def __init__(self, *, loop: asyncio.AbstractEventLoop | None = None,
                 epoch: float | None = None, max_catchup: int = 50,
                 cpu_threads: int | None = 1, compress_mesh: bool = True,
                 capacity: int | None = None, spool_dir: Path | None = None,
                 manual_clock: bool = False, cpu_loops: int | None = None) -> None:
        self.loop = loop
        self.manual_clock = manual_clock
        self._manual_now = 0.0
        # Server time zero, on the clock the loops keep (time.perf_counter is
        # CLOCK_MONOTONIC, as the native loop's).
        epoch = 0.0 if manual_clock else (time.perf_counter() if epoch is None else epoch)
        self.epoch = epoch
        # One CPU thread per worker by default: on a small machine a second OpenMP thread
        # competes with the event loop for the cores, and its spinning barriers then cost
        # whole slices (`clothball host --workers` spreads rooms over processes instead).
        self.settings = LoopSettings(epoch=epoch, max_catchup=max_catchup,
                                     cpu_threads=cpu_threads, compress_mesh=compress_mesh,
                                     manual_clock=manual_clock)
        loop_rooms_default()  # a bad CLOTHBALL_LOOP_ROOMS is refused here, at once
        self._capacity = capacity  # None: each backend's (capacity_for)
        # The CPU engine's frame loops a scene's rooms are spread over (None: cpu_loops_default()).
        self.cpu_loops = cpu_loops_default() if cpu_loops is None else cpu_loops
        # Where recordings spool while a round lasts (the data directory's, for a server).
        self.spool_dir = spool_dir or Path(tempfile.gettempdir()) / "clothball-spool"
        self._workers: dict[tuple[str, str, str, int, int], list[FrameWorker]] = {}
        self._lock = threading.Lock()
        self._wakes: set[int] = set()  # eventfds every frame loop writes each pass

    def capacity_for(self, backend: str) -> int:
        """The rooms one worker of ``backend`` (resolved: "cpu" or "cuda") holds."""
        return loop_rooms_default(backend) if self._capacity is None else self._capacity

    def now(self) -> float:
        """Server time: seconds since the pool's epoch (with a manual clock, its time)."""
        return self._manual_now if self.manual_clock else time.perf_counter() - self.epoch

    def set_clock(self, t: float) -> None:
        """A manual clock's time, s: every loop steps the frames due by then."""
        if not self.manual_clock:
            raise ValueError("set_clock: this pool keeps the monotonic clock "
                             "(make it with manual_clock=True)")
        self._manual_now = float(t)
        for w in self.workers:
            w.set_clock(self._manual_now)

    def worker_for(self, scene: Scene, backend: str, mesh_every: int,
                   track_every: int) -> FrameWorker:
        """A worker with room for one more room of ``scene`` (started if new)."""
        if self.loop is None:
            try:  # results are handed to the loop the rooms are made on
                self.loop = asyncio.get_running_loop()
            except RuntimeError:
                pass
        resolved, precision, _ = resolve_backend(scene, backend, None)
        key = (json.dumps(scene.to_dict(), sort_keys=True), resolved, precision,
               mesh_every, track_every)
        with self._lock:
            workers = self._workers.setdefault(key, [])
            open_ = [w for w in workers if not w.full]
            # A new worker while every open one has rooms and the CPU's spread allows it;
            # else the open worker with the fewest rooms.
            spread = resolved == "cpu" and len(workers) < self.cpu_loops and \
                all(w.members for w in open_)
            if open_ and not spread:
                w = min(open_, key=lambda w: w.members)
            else:
                w = FrameWorker(scene, resolved, self.capacity_for(resolved), self.settings,
                                mesh_every, track_every)
                for fd in self._wakes:
                    w.add_wake(fd)
                workers.append(w)
                w.start()
                if self.manual_clock:
                    w.set_clock(self._manual_now)
            if self.loop is not None:
                w.watch(self.loop)
            w.members += 1
            return w

    def set_wake(self, fd: int, on: bool) -> None:
        """An eventfd written by every frame loop, now and to come, once a pass (``on``),
        or no more (a gateway's: ``server.shared.lanes``)."""
        with self._lock:
            (self._wakes.add if on else self._wakes.discard)(fd)
            for w in (w for ws in self._workers.values() for w in ws):
                (w.add_wake if on else w.remove_wake)(fd)

    def local_shares(self) -> list[tuple[int, Any, str, object]]:
        """Every worker's block and board, as this process's lanes read them."""
        return [share for w in self.workers for share in w.local_shares()]

    def shares(self) -> list[tuple[int, int, int, str]]:
        """The blocks and boards as the gateways map them (id, memfd, bytes, kind): those
        in memory another process can map."""
        out = []
        for w in self.workers:
            if w.block_share[1] >= 0:
                out.append((*w.block_share, "block"))
            if w.board_share is not None:
                out.append((*w.board_share, "board"))
        return out

    @property
    def workers(self) -> list[FrameWorker]:
        with self._lock:
            return [w for ws in self._workers.values() for w in ws]

    def close(self) -> None:
        for w in self.workers:
            w.stop()
        with self._lock:
            self._workers.clear()
