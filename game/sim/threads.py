"""How many threads the CPU engine runs, chosen by the work a frame has and the cores free
now (issue 40).

Every substep the threads of one cloth meet at barriers. A thread's share must be worth
those meetings, and every thread must have a core: one that waits for a core held by
another program holds the others up at each barrier. On the 2-core VM beside two busy
loops, two threads took ~12 500 us a substep where one took 17.5 us quiet. So: one
thread per ``MIN_NODES_PER_THREAD`` nodes of a frame's work, at most the cores free now
(``free_cores``), at least one.

The OpenMP threads also *sleep* between parallel regions (``OMP_WAIT_POLICY=PASSIVE``,
set in ``clothball.game.sim`` before the native module is loaded, unless the environment
says otherwise): spinning, they took the cores between frames from everything else.
"""

from __future__ import annotations

import os
import threading
import time

# A thread's share of a frame below this many nodes costs more at its barriers than it
# saves. Measured on the quiet 2-core VM (`python tools/thread_threshold.py`, classic,
# float32, 2026-11-28), two threads against one a substep: 1.47x the time at 16 384 nodes,
# 1.45 at 32 761, 1.06 at 40 000, 0.86 at 50 176, 0.83 at 65 536, 0.82 at 90 000 (the passive
# barriers' wake-ups cost ~50-80 us a substep there). So a second thread from ~49 000 nodes.
MIN_NODES_PER_THREAD = 24576
SAMPLE_S = 0.02  # the shortest look at /proc/stat that says how busy the machine is
FRESH_S = 1.0  # a look this recent is reused

_lock = threading.Lock()
# The last look: (monotonic, busy jiffies, all jiffies, this process's CPU seconds).
_last: tuple[float, int, int, float] | None = None
_free: tuple[float, float] | None = None  # (monotonic, free cores) of the last look


def usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _jiffies() -> tuple[int, int] | None:
    """(busy, all) CPU time of the machine so far; None where /proc/stat is not."""
    try:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:8]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    return sum(fields) - idle, sum(fields)


def free_cores() -> float:
    """Cores no other program is using now: the machine's idle share since the last look
    (at least ``SAMPLE_S``; a look ``FRESH_S`` old is reused), this process's own CPU time
    counted as free (its cloths are what will use it). Every usable core where /proc/stat
    cannot be read."""
    global _last, _free
    cores = usable_cores()
    with _lock:
        now = time.monotonic()
        if _free is not None and now - _free[0] < FRESH_S:
            return _free[1]
        cur = _jiffies()
        if cur is None:
            return float(cores)
        base = _last
        if base is None or now - base[0] > 10 * FRESH_S or now - base[0] < SAMPLE_S:
            base = (now, *cur, time.process_time())
            time.sleep(SAMPLE_S)
            now, cur = time.monotonic(), _jiffies() or cur
        own_cpu = time.process_time()
        _last = (now, *cur, own_cpu)
        total = cur[1] - base[2]
        if total <= 0:
            return float(cores)
        machine = os.cpu_count() or cores
        own = (own_cpu - base[3]) / max(now - base[0], 1e-3) / machine
        others = max((cur[0] - base[1]) / total - own, 0.0)
        free = min(float(cores), machine * (1.0 - others))
        _free = (now, free)
        return free


def choose(nodes: int, requested: int | None = None) -> int:
    """Threads for a frame of ``nodes`` nodes' work: ``requested`` where given, else one
    per ``MIN_NODES_PER_THREAD`` nodes, at most the cores free now, at least one."""
    if requested is not None:
        return requested
    from ... import _native  # type: ignore[attr-defined]  # (loaded by now: the caller's)

    # OMP_NUM_THREADS, where set, still caps them (the OpenMP runtime's own count).
    most = min(usable_cores(), _native.cpu_threads())
    by_work = min(max(1, nodes // MIN_NODES_PER_THREAD), most)
    if by_work == 1:
        return 1  # no need to look at the machine
    return max(1, min(by_work, int(free_cores() + 0.5)))


def busy_note() -> str | None:
    """A warning for a benchmark when other programs use the cores now, else None."""
    cores = usable_cores()
    others = cores - free_cores()
    if others < 0.5:
        return None
    return (f"warning: this machine is busy: about {others:.1f} of its {cores} cores are in "
            "use by other programs; the CPU engine runs on the cores free (the threads "
            "column) and its figures are slower than a quiet machine's")
