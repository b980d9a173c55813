"""What a sim worker hands the event loop (``FrameResult``), and the fixed-size ring its
lateness is kept in (``Samples``): shared by both frame loops (``server.sim``'s Python one
and ``server.frameloop``'s native one)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class FrameResult:
    """The state after the newest frame, as the event loop receives it."""

    frame: int
    server_time: float
    corners: list[bytes | None]  # one CORNER message per seat (None: not for its occupant)
    mesh: bytes | None = None  # newest MESH message, when one was made since the last delivery
    exit: tuple[int, int, list[float]] | None = None  # (edge, frame, ball position)
    sim_error: str | None = None
    # Per seat, the occupant the CORNER's HIP echo belongs to (RoomSim.set_hip's count).
    occupants: tuple[int, ...] = ()

    def merge_older(self, prev: FrameResult) -> None:
        """Coalesce: keep this (newer) frame, but never lose a mesh, an exit or an error."""
        if self.mesh is None:
            self.mesh = prev.mesh
        if self.exit is None:
            self.exit = prev.exit
        if self.sim_error is None:
            self.sim_error = prev.sim_error


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

    def newest(self, n: int | None = None) -> np.ndarray:
        k = len(self) if n is None else max(0, min(n, len(self)))
        end = self._end()
        idx = np.arange(end - k, end) % len(self._a)
        return self._a[idx]

    def clear(self) -> None:
        self.count = 0
