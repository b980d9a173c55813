"""How much more this server can take, measured by itself: the admission control.

Every ``WINDOW_S`` the server looks at what its rooms did since the last look: the frame
lateness of its simulation workers (p99 of every pass: when a frame's state was ready
against its deadline), frames they had to skip, and the CPU the process used. It is *busy*
while each of the last ``SUSTAINED`` windows had a lateness p99 past ``admit_lateness_ms``
or skipped frames (a hiccup is not saturation; an overload lasts):
then a new room, or anyone waking a sleeping room, is refused with ``server_busy`` and the
reason, before the rooms already running degrade further; and a host that is busy takes
no new rooms from the others (``docs/cluster.md``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .sim import SimPool

WINDOW_S = 1.0
SUSTAINED = 3  # windows in a row over the limit that make the server busy


@dataclass
class Sample:
    lateness_p99_ms: float = 0.0
    skipped_frames: int = 0
    cpu_cores: float = 0.0  # process CPU time over wall time in the window


class Headroom:
    def __init__(self, sims: SimPool, lateness_ms: float) -> None:
        self.sims = sims
        self.lateness_ms = lateness_ms
        self.last = Sample()
        self.recent: list[Sample] = []  # the last SUSTAINED windows, newest last
        self._cpu = time.process_time()
        self._wall = time.perf_counter()
        self._seen: dict[int, tuple[int, int]] = {}  # worker id -> (lateness seen, skipped)

    def sample(self) -> Sample:
        """Look at the window since the last call (the server calls it every WINDOW_S)."""
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
        window = np.concatenate(late) if late else np.zeros(0)
        p99 = float(np.percentile(window, 99)) * 1e3 if window.size else 0.0
        self.last = Sample(p99, skipped, cores)
        self.recent = [*self.recent, self.last][-SUSTAINED:]
        return self.last

    def _over(self, s: Sample) -> bool:
        return s.skipped_frames > 0 or s.lateness_p99_ms > self.lateness_ms

    @property
    def busy(self) -> str | None:
        """Why no more rooms fit now (None: there is room)."""
        if self.lateness_ms <= 0 or len(self.recent) < SUSTAINED:
            return None
        if not all(self._over(s) for s in self.recent):
            return None
        s = self.last
        return (f"this server is at capacity: for {SUSTAINED} s its frames were late (p99 "
                f"{s.lateness_p99_ms:.1f} ms, limit {self.lateness_ms:g} ms) or skipped "
                f"({s.skipped_frames} in the last second) at {s.cpu_cores:.2f} CPU cores; try "
                "again later or another server")
