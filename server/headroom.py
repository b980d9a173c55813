"""How much more this server can take: the admission control.

A new room is admitted or refused *before it exists*, from what it will cost: each scene's
room costs the cores ``room_cost`` measured for it on this machine and backend (once per
process, at start-up). On the CPU backend the native frame loop (``server.sim.worker``)
runs one room, then ``CALIBRATE_ROOMS_NATIVE``, and its thread's CPU time over the frames it
*stepped* gives what a frame of each costs: a room the difference, the thread the rest (its
pacing and publishing, once a thread). Frames it skipped, falling behind, cost nothing and
are not counted, so a loop that cannot keep up measures a room at its true price, and CPU
stolen by neighbours does not inflate it. On a GPU four rooms are stepped, one
``ClothBatch`` call a frame, and 64 rooms, so that the launch all of a worker's rooms share
counts once per thread. Every open room
counts, asleep or awake (a sleeping room wakes the moment someone joins it). A room fits
while the rooms' cost stays within ``admit_load`` of the cores the process may use, and
within ``admit_load`` of one core for the rooms one simulation thread steps (one per scene,
``server.sim``). A burst of ``create_room`` is therefore refused at once past the capacity,
with the numbers; an empty server always admits its first room.

Besides the model, every ``WINDOW_S`` the server looks at what its rooms did since the last
look: the frame lateness of its simulation workers (p99 of every pass), frames they had to
skip, the CPU the process used and the machine's stolen CPU (``/proc/stat``). It is *busy*
while each of the last ``SUSTAINED`` windows had a lateness p99 past ``admit_lateness_ms``
or skipped frames: they are its own rooms' frames, and another room would be late too,
whatever the CPU figure. Where the process itself used little CPU (under
``OWN_LOAD_CORES``, its rooms costing less by the model) the refusal also names the cause,
CPU taken from outside (``outside``: neighbours, steal), but refuses all the same. While
busy, a new room or the waking of a sleeping one is refused with ``server_busy`` and the
reason, and a host that is busy takes no new rooms from the others (``docs/cluster.md``).
"""

from __future__ import annotations

import collections
import json
import math
import os
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ..game.sim.batch import ClothBatch
from ..game.sim.cloth import resolve_backend
from ..game.sim.scene import Scene
from .sim import RoomSim, SimPool

WINDOW_S = 1.0
SUSTAINED = 3  # windows in a row over the limit that make the server busy
# The process used at least this many cores in a late window: the lateness is its own
# load. Less: something else took the CPU (steal, neighbours), which the refusal names.
OWN_LOAD_CORES = 0.5
CALIBRATE_S = 0.15  # s of stepping that measure one scene's room cost
CALIBRATE_ROOMS = 4
# A GPU steps every room of a worker in one launch: most of a frame's cost is the launch,
# whatever the rooms. It is measured at two sizes, so the launch counts once per thread and
# a room only its share beyond it (at 4 rooms alone the launch made a room look ~20 times
# dearer on an H100: 20 rooms a thread instead of the hundreds it steps).
CALIBRATE_ROOMS_GPU = 64
# The native loop on the CPU: its thread's CPU time over the frames it *stepped*, with one
# room and with CALIBRATE_ROOMS_NATIVE, so that a room costs what its frames cost and the
# loop's own work a pass (pacing, publishing) counts once a thread. Shared out over wall
# time instead, a thread that could not keep up (16 rooms of the default scene need ~5.5
# cores on the 2-core VM) made a room look 0.06 cores where it costs 0.34, and admission
# took 11-31 rooms that ran at 0.03-0.25x real time (issue 40).
CALIBRATE_ROOMS_NATIVE = 8
CALIBRATE_WARM_S = 0.05
CALIBRATE_MIN_FRAMES = 20  # frames a native measure waits for past CALIBRATE_S ...
CALIBRATE_MAX_S = 5.0  # ... for at most this long

# key -> (cores the stepping thread costs whatever its rooms, cores a room adds)
_costs: dict[tuple[str, str, str], tuple[float, float]] = {}
_costs_lock = threading.Lock()


def _key(scene: Scene, backend: str) -> tuple[str, str, str]:
    resolved, precision, _ = resolve_backend(scene, backend, None)
    return json.dumps(scene.to_dict(), sort_keys=True), resolved, precision


def _frame_cost(scene: Scene, key: tuple[str, str, str], rooms: int) -> float:
    """Cores a thread spends stepping ``rooms`` rooms of ``scene`` at real time, one
    ``ClothBatch`` call a frame (the GPU's measure; on the CPU a reference for the loop's)."""
    batch = ClothBatch(scene, rooms, key[1], key[2], threads=1)
    for _ in range(rooms):
        batch.add()
    batch.step(2)  # first-call costs (allocation, JIT of nothing) out of the measure
    # On the CPU the stepping thread's own CPU time (not inflated by time stolen from it);
    # a GPU's cost is the wall time of a step, which the thread waits out.
    clock = time.thread_time if key[1] == "cpu" else time.perf_counter
    wall0, t0, frames = time.perf_counter(), clock(), 0
    while frames < 2000 and time.perf_counter() - wall0 < CALIBRATE_S:
        batch.step(1)
        batch.corners_all()
        frames += 1
    return (clock() - t0) / max(frames, 1) / batch.frame_dt


def _native_cost(scene: Scene, backend: str, rooms: int) -> float:
    """Cores the native frame loop's thread would spend on ``rooms`` awake rooms of
    ``scene`` at real time: its CPU time over the frames it stepped (frames skipped because
    it fell behind cost nothing and are not counted)."""
    pool = SimPool(cpu_loops=1)  # (one loop's thread stepping them all)
    sims: list[RoomSim] = []
    try:
        for _ in range(rooms):
            sims.append(RoomSim(scene, backend, pool=pool))
            sims[-1].start()
        worker = sims[0].worker
        time.sleep(CALIBRATE_WARM_S)
        cpu0, frames0 = worker.cpu_seconds(), sims[0].stats.frames
        wall0 = time.perf_counter()
        # At least a few frames, however slow the machine (every room steps each frame).
        while time.perf_counter() - wall0 < CALIBRATE_S or \
                sims[0].stats.frames - frames0 < CALIBRATE_MIN_FRAMES:
            if time.perf_counter() - wall0 > CALIBRATE_MAX_S:
                break
            time.sleep(0.01)
        cpu, frames = worker.cpu_seconds() - cpu0, sims[0].stats.frames - frames0
        return cpu / (max(frames, 1) * sims[0].frame_dt)
    finally:
        for s in sims:
            s.stop()
        pool.close()


def _measure(scene: Scene, backend: str) -> tuple[float, float]:
    key = _key(scene, backend)
    with _costs_lock:
        if key in _costs:
            return _costs[key]
    if key[1] == "cpu":  # per room from the difference; the rest is the thread's own
        one = _native_cost(scene, backend, 1)
        many = _native_cost(scene, backend, CALIBRATE_ROOMS_NATIVE)
        per_room = (many - one) / (CALIBRATE_ROOMS_NATIVE - 1)
        if per_room <= 0.0:  # noise swamped the difference: the whole share, dearer
            per_room = many / CALIBRATE_ROOMS_NATIVE
        cost = (max(one - per_room, 0.0), per_room)
    else:
        small = _frame_cost(scene, key, CALIBRATE_ROOMS)
        large = _frame_cost(scene, key, CALIBRATE_ROOMS_GPU)
        per_room = max(large - small, 0.0) / (CALIBRATE_ROOMS_GPU - CALIBRATE_ROOMS)
        cost = (max(small - CALIBRATE_ROOMS * per_room, 0.0), per_room)
    with _costs_lock:
        _costs[key] = cost
    return cost


def room_cost(scene: Scene, backend: str) -> float:
    """Cores one room of ``scene`` adds on ``backend`` at real time (measured once per
    process; blocking: call it off the event loop)."""
    return _measure(scene, backend)[1]


def thread_cost(scene: Scene, backend: str) -> float:
    """Cores the thread stepping ``scene``'s rooms costs whatever their number (measured
    with ``room_cost``)."""
    return _measure(scene, backend)[0]


@dataclass
class Sample:
    lateness_p99_ms: float = 0.0
    skipped_frames: int = 0
    cpu_cores: float = 0.0  # process CPU time over wall time in the window
    carried_cores: float = 0.0  # what its awake rooms cost by the model
    steal: float = 0.0  # share of the machine's CPU time stolen by the hypervisor (Linux)


def _cpu_times() -> tuple[int, int] | None:
    """(steal, total) jiffies of the machine so far; None where /proc/stat is not."""
    try:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    return (fields[7] if len(fields) > 7 else 0), sum(fields[:8])


def usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


class Headroom:
    def __init__(self, sims: SimPool, lateness_ms: float, *, load: float = 0.75,
                 cores: float = 0.0, backend: str = "auto") -> None:
        """``lateness_ms``: the measured signal's limit (0: off); ``load``: the share of the
        ``cores`` (0: those this process may use) the rooms' cost may take (0: no cost
        model)."""
        self.sims = sims
        self.lateness_ms = lateness_ms
        self.load = load
        self.cores = cores or float(usable_cores())
        self.backend = backend
        self.last = Sample()
        self.recent: list[Sample] = []  # the last SUSTAINED windows, newest last
        self._cpu = time.process_time()
        self._wall = time.perf_counter()
        self._steal = _cpu_times()
        self._seen: dict[int, tuple[int, int]] = {}  # worker id -> (lateness seen, skipped)

    # --- the cost model ---------------------------------------------------------------------
    def measure(self, scenes: Iterable[Scene]) -> None:
        """Every scene's room cost measured now (blocking: at start-up, off the loop)."""
        for scene in scenes:
            _measure(scene, self.backend)

    def cost(self, scene: Scene) -> float:
        """A room of ``scene``'s cost in cores (as measured; 0 if not measured yet)."""
        with _costs_lock:
            return _costs.get(_key(scene, self.backend), (0.0, 0.0))[1]

    def thread_cost(self, scene: Scene) -> float:
        """What the thread that steps ``scene``'s rooms costs whatever their number (the CPU
        loop's pacing and publishing, a GPU's launch; 0 if not measured yet)."""
        with _costs_lock:
            return _costs.get(_key(scene, self.backend), (0.0, 0.0))[0]

    def refusal(self, scene: Scene, rooms: list[Scene]) -> str | None:
        """Why a new room of ``scene`` would not fit beside the open ``rooms`` (their
        scenes), or None. Then the measured signal (``busy``)."""
        if self.load > 0 and rooms:
            keys = [_key(s, self.backend) for s in rooms]
            key = _key(scene, self.backend)
            with _costs_lock:  # (fixed, per room) of each scene, 0 where not measured
                cost = {k: _costs.get(k, (0.0, 0.0)) for k in {*keys, key}}
            fixed, need = cost[key]
            # A scene's rooms share one stepping thread, or on the CPU engine up to
            # ``cpu_loops`` by turns: a thread's fixed cost counted once a thread.
            counts = collections.Counter(keys)
            counts[key] += 1
            total = sum(cost[k][1] for k in keys) + \
                sum(cost[k][0] * self._threads(k, n) for k, n in counts.items())
            budget = self.load * self.cores
            if total + need > budget:
                return (f"this server is at capacity: its {len(rooms)} rooms need about "
                        f"{total:.2f} of the {budget:.2f} cores it gives rooms "
                        f"({self.load:.0%} of {self.cores:g}) and a {scene.name} room "
                        f"{need:.2f} more; try again later or another server")
            on_thread = self._on_thread(key, keys.count(key))  # the rooms its thread steps
            if on_thread and fixed + (on_thread + 1) * need > self.load:
                return (f"this server is at capacity for {scene.name}: its simulation "
                        f"thread steps {on_thread} such rooms at about {need:.3f} of a core "
                        f"each (and {fixed:.2f} whatever their number), and may use "
                        f"{self.load:.0%} of one; try another scene, later, or another server")
        return self.busy

    def _loops(self, key: tuple[str, str, str]) -> int:
        return max(1, int(getattr(self.sims, "cpu_loops", 1))) if key[1] == "cpu" else 1

    def _threads(self, key: tuple[str, str, str], rooms: int) -> int:
        """The threads that step ``rooms`` rooms of ``key`` (SimPool.worker_for): a worker
        for each worker's capacity of rooms, and on the CPU engine up to ``cpu_loops`` by
        turns before any is full."""
        full = -(-rooms // self.sims.capacity_for(key[1]))
        return max(min(rooms, self._loops(key)), full) if key[1] == "cpu" else full

    def _on_thread(self, key: tuple[str, str, str], rooms: int) -> int:
        """The rooms already on the thread a new room of ``key`` would go to, beside
        ``rooms`` of them (the CPU's: the loop with the fewest)."""
        if key[1] == "cpu":
            return rooms // self._loops(key)
        return rooms % self.sims.capacity_for(key[1])

    # --- the measured signal ----------------------------------------------------------------
    def sample(self, awake: Iterable[Scene] = ()) -> Sample:
        """Look at the window since the last call (the server calls it every WINDOW_S, with
        the scenes of its awake rooms)."""
        late: list[np.ndarray] = []
        skipped = 0
        seen: dict[int, tuple[int, int]] = {}
        for w in self.sims.workers:
            n0, s0 = self._seen.get(id(w), (0, 0))
            n = w.lateness.count
            late.append(w.lateness.since(n0))
            s = w.skipped_frames
            skipped += s - s0
            seen[id(w)] = (n, s)
        self._seen = seen
        cpu, wall = time.process_time(), time.perf_counter()
        cores = (cpu - self._cpu) / max(wall - self._wall, 1e-9)
        self._cpu, self._wall = cpu, wall
        steal = 0.0
        now = _cpu_times()
        if now is not None and self._steal is not None and now[1] > self._steal[1]:
            steal = (now[0] - self._steal[0]) / (now[1] - self._steal[1])
        self._steal = now
        window = np.concatenate(late) if late else np.zeros(0)
        p99 = float(np.percentile(window, 99)) * 1e3 if window.size else 0.0
        self.last = Sample(p99, skipped, cores, sum(self.cost(s) for s in awake),
                           steal if math.isfinite(steal) else 0.0)
        self.recent = [*self.recent, self.last][-SUSTAINED:]
        return self.last

    def _late(self, s: Sample) -> bool:
        return s.skipped_frames > 0 or s.lateness_p99_ms > self.lateness_ms

    @staticmethod
    def _own(s: Sample) -> bool:
        return max(s.cpu_cores, s.carried_cores) >= OWN_LOAD_CORES

    @property
    def outside(self) -> str | None:
        """Late frames while this server itself uses little CPU: the cause named (CPU taken
        by other programs or the hypervisor), or None. Its rooms are late all the same, so
        it makes the server no less busy (``busy``)."""
        s = self.last
        if self.lateness_ms <= 0 or not self._late(s) or self._own(s):
            return None
        return (f"frames late (p99 {s.lateness_p99_ms:.1f} ms, {s.skipped_frames} skipped) "
                f"while this server used {s.cpu_cores:.2f} cores and its rooms cost "
                f"{s.carried_cores:.2f}: CPU taken from outside ({s.steal:.0%} stolen)")

    @property
    def busy(self) -> str | None:
        """Why no more rooms fit now by the measured signal (None: there is room): frames
        of this server's own rooms late or skipped in each of the last ``SUSTAINED``
        windows, whatever CPU it used (another room would be late too)."""
        if self.lateness_ms <= 0 or len(self.recent) < SUSTAINED:
            return None
        if not all(self._late(s) for s in self.recent):
            return None
        s = self.last
        why = self.outside
        return (f"this server is at capacity: for {SUSTAINED} s its frames were late (p99 "
                f"{s.lateness_p99_ms:.1f} ms, limit {self.lateness_ms:g} ms) or skipped "
                f"({s.skipped_frames} in the last second) at {s.cpu_cores:.2f} CPU cores"
                + (f"; {why}" if why else "") + "; try again later or another server")
