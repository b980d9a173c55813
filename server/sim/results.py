"""What a room's frame loop hands the event loop after a frame (``FrameResult``), and the
fixed-size ring lateness is kept in (``Samples``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class FrameResult:
    """A room's state after its newest frame, as the event loop receives it (its MESH comes
    on its own: ``RoomSim``'s ``deliver_mesh``)."""

    frame: int
    server_time: float
    corners: list[bytes | None]  # one CORNER message per seat (None: not for its occupant)
    exit: tuple[int, int, list[float]] | None = None  # (edge, frame, ball position)
    sim_error: str | None = None
    # Per seat, the occupant the CORNER's HIP echo belongs to (RoomSim.set_hip's count).
    occupants: tuple[int, ...] = ()


class Samples:
    """The newest ``capacity`` float samples in a ring of fixed size: the memory is taken
    once, whatever the number of samples (a list grew and shrank with them)."""

    def __init__(self, capacity: int) -> None:
        self._a = np.zeros(capacity)
        self.count = 0  # samples appended since the last clear

    def append(self, value: float) -> None:
        self._a[self.count % len(self._a)] = value
        self.count += 1

    def __len__(self) -> int:
        return min(self.count, len(self._a))

    def since(self, count: int) -> np.ndarray:
        """The samples appended after the first ``count`` (the newest ones kept), in order."""
        n = min(self.count - count, len(self)) if count <= self.count else len(self)
        return self.newest(n)

    def _end(self) -> int:
        """The ring position after the newest sample, counted from the ring's start."""
        return self.count

    def key(self) -> tuple[int, int]:
        """The ring and how many samples are kept: views of one ring with equal keys, read
        at the same moment, hold the same samples, and figures made from one serve the
        others (``/api/stats``: every room of a frame loop shares its lateness ring; the
        percentiles of 100 000 samples take ~3 ms on the 2-core VM, so 256 rooms' held the
        event loop up for about a second a call). The ring's end is not in it: a frame loop
        appends a sample each frame while the rooms are read, so a key with the end matched
        almost no other room (the H200 at 256 rooms: ``/api/stats`` p50 100 ms, the
        percentiles most of it); views read a moment apart differ by those frames only."""
        return self._a.ctypes.data, len(self)  # (views share the memory)

    def newest(self, n: int | None = None) -> np.ndarray:
        k = len(self) if n is None else max(0, min(n, len(self)))
        end = self._end()
        idx = np.arange(end - k, end) % len(self._a)
        return self._a[idx]

    def clear(self) -> None:
        self.count = 0
