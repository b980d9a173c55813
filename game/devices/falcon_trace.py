"""A recorded Falcon: replays a trace of (time, position, buttons) as a ``base.Device``.

A trace is a CSV file with the header ``t,x,y,z,buttons``: seconds from the start, the
grip position in the Falcon's device frame (metres; see ``docs/falcon.md``) and the button
mask. ``record_trace`` writes one from a running ``FalconDevice``; ``TraceDevice`` plays it
back through the same cube-to-reach mapping as the live device, linearly interpolated, so
a real session can be replayed into the game (or tests) without the hardware.
"""

from __future__ import annotations

import csv
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .base import CornerState, Reach
from .falcon import FalconDevice, FalconMapping

HEADER = ("t", "x", "y", "z", "buttons")


class TraceError(ValueError):
    """The trace file is missing, empty or malformed."""


def load_trace(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (n,), device positions (n, 3) and buttons (n,) of a trace file."""
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as e:
        raise TraceError(f"cannot read the trace {path}: {e.strerror}") from e
    if not rows or tuple(c.strip() for c in rows[0]) != HEADER:
        raise TraceError(f"{path}: the first line must be {','.join(HEADER)}")
    try:
        data = np.array([[float(v) for v in r] for r in rows[1:] if r], dtype=np.float64)
    except ValueError as e:
        raise TraceError(f"{path}: {e}") from e
    if data.ndim != 2 or len(data) == 0 or data.shape[1] != 5:
        raise TraceError(f"{path}: no samples")
    if not np.all(np.isfinite(data)) or np.any(np.diff(data[:, 0]) < 0):
        raise TraceError(f"{path}: times must be finite and non-decreasing")
    return data[:, 0] - data[0, 0], data[:, 1:4], data[:, 4].astype(np.int64)


class TraceDevice:
    """Replays a recorded trace; implements ``base.Device`` (no force feedback)."""

    name = "falcon-trace"

    def __init__(self, path: str | os.PathLike[str], *, loop: bool = True,
                 clock: Callable[[], float] = time.monotonic,
                 axis_signs: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> None:
        self.times, self.positions, self.button_masks = load_trace(path)
        self.loop = loop
        self._clock = clock
        self._signs = axis_signs
        self._t0: float | None = None
        self.mapping: FalconMapping | None = None
        self.corner: CornerState | None = None

    def start(self, reach: Reach) -> None:
        self.mapping = FalconMapping(reach, self._signs)
        self._t0 = self._clock()

    def stop(self) -> None:
        self._t0 = None

    def _elapsed(self) -> float:
        if self._t0 is None:
            raise RuntimeError("TraceDevice.start(reach) first")
        t = self._clock() - self._t0
        duration = float(self.times[-1])
        if self.loop and duration > 0:
            t %= duration
        return min(t, duration)

    def device_position(self) -> np.ndarray:
        t = self._elapsed()
        return np.array([np.interp(t, self.times, self.positions[:, k]) for k in range(3)])

    def hand_position(self) -> np.ndarray:
        assert self.mapping is not None
        return self.mapping.reach.clamp(self.mapping.to_world(self.device_position()))

    def buttons(self) -> int:
        i = int(np.searchsorted(self.times, self._elapsed(), side="right")) - 1
        return int(self.button_masks[max(i, 0)])

    def update_corner(self, state: CornerState) -> None:
        self.corner = state


def record_trace(device: FalconDevice, path: str | os.PathLike[str], seconds: float,
                 rate: float = 250.0) -> int:
    """Samples a started FalconDevice into a trace file; returns the number of samples."""
    period = 1.0 / rate
    t0 = time.monotonic()
    n = 0
    with Path(path).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(HEADER)
        while (t := time.monotonic() - t0) < seconds:
            snap = device.snapshot()
            w.writerow([f"{t:.6f}", *(f"{v:.7f}" for v in snap["position"]), snap["buttons"]])
            n += 1
            time.sleep(max(0.0, t0 + n * period - time.monotonic()))
    return n
