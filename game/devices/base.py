"""The one small interface every input device shares (mouse, bot, Falcon).

A device produces the hand position h (the haptic interface point, world metres) for the
corner its player holds, inside that corner's reach box, and is told the latest corner
state the server sent, so a force-feedback device can render F = -K (h - c) locally.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class Reach:
    """The box a corner's hand may move in: ``centre`` +/- ``half_extent`` (world metres)."""

    centre: np.ndarray
    half_extent: np.ndarray

    def clamp(self, h: np.ndarray) -> np.ndarray:
        lo, hi = self.centre - self.half_extent, self.centre + self.half_extent
        return np.clip(np.asarray(h, dtype=np.float64), lo, hi)

    def from_unit(self, u: np.ndarray) -> np.ndarray:
        """Map a point of the unit cube [-1, 1]^3 onto the box (clamped)."""
        u = np.clip(np.asarray(u, dtype=np.float64), -1.0, 1.0)
        return self.centre + u * self.half_extent


@dataclass
class CornerState:
    """What the server says about one corner each frame (see docs/protocol.md)."""

    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    force: np.ndarray = field(default_factory=lambda: np.zeros(3))  # on the device, N
    stiffness: float = 0.0  # coupling K, N/m
    frame: int = 0
    server_time: float = 0.0  # seconds, server clock
    ball_position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    ball_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    received_at: float = 0.0  # seconds, local monotonic clock


@runtime_checkable
class Device(Protocol):
    """An input device for one corner."""

    name: str

    def start(self, reach: Reach) -> None:
        """Begin producing hand positions inside ``reach``."""

    def stop(self) -> None:
        """Release the device; safe to call twice."""

    def hand_position(self) -> np.ndarray:
        """The latest hand position h (3,), world metres, inside the reach box."""

    def update_corner(self, state: CornerState) -> None:
        """The latest corner state from the server (force feedback, displays)."""
