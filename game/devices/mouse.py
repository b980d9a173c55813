"""The mouse as a clothball input device (implements ``devices.base.Device``).

The mouse moves the hand in the horizontal plane and the wheel (or a right-button drag)
moves it up and down, always inside the corner's reach box. The window turns a pointer
position into a ray through the camera (``point_at_ray``): the hand goes where the ray
meets the horizontal plane at the hand's current height, so the hand stays under the
cursor on screen. Without a camera, ``set_unit`` maps a point of [-1, 1]^2 straight onto
the box's horizontal extent.

A mouse cannot push back, so the device keeps the latest corner state for the window to
*show* the pull: the line from the cloth's corner to the hand and the coupling force
``|F| = K |h - c|`` (``pull()``).

Thread safety: the window thread moves the hand, the network thread reads it and feeds
corner states; a lock guards both.
"""

from __future__ import annotations

import threading

import numpy as np

from .base import CornerState, Reach


class MouseDevice:
    """Hand position from pointer, wheel and right-drag; implements ``base.Device``."""

    name = "mouse"

    def __init__(self, wheel_step: float = 0.08, drag_gain: float = 0.006) -> None:
        """``wheel_step``: height change per wheel click, as a fraction of the box's
        vertical half extent; ``drag_gain``: the same per pixel of right-button drag."""
        self.wheel_step = float(wheel_step)
        self.drag_gain = float(drag_gain)
        self.reach: Reach | None = None
        self._lock = threading.Lock()
        self._hand = np.zeros(3)
        self._corner = CornerState()
        self._has_corner = False
        self.moves = 0  # how many inputs moved the hand (the window's tests read it)

    # --- base.Device ----------------------------------------------------------------------
    def start(self, reach: Reach) -> None:
        with self._lock:
            self.reach = reach
            self._hand = np.asarray(reach.centre, dtype=np.float64).copy()

    def stop(self) -> None:
        with self._lock:
            self.reach = None

    def hand_position(self) -> np.ndarray:
        with self._lock:
            return self._hand.copy()

    def update_corner(self, state: CornerState) -> None:
        with self._lock:
            self._corner = state
            self._has_corner = True

    # --- inputs ---------------------------------------------------------------------------
    def _set(self, h: np.ndarray) -> None:
        """Callers hold the lock."""
        if self.reach is None:
            return
        h = np.asarray(h, dtype=np.float64)
        if not np.all(np.isfinite(h)):
            return
        new = self.reach.clamp(h)
        if not np.array_equal(new, self._hand):
            self.moves += 1
        self._hand = new

    def set_unit(self, u: float, w: float) -> None:
        """Horizontal position from unit coordinates: ``u`` along x, ``w`` along z, each
        in [-1, 1] across the reach box (clamped); the height is kept."""
        with self._lock:
            if self.reach is None:
                return
            target = self.reach.from_unit(np.array([u, 0.0, w]))
            self._set(np.array([target[0], self._hand[1], target[2]]))

    def set_horizontal(self, x: float, z: float) -> None:
        """Horizontal position in world metres (clamped to the box); the height is kept."""
        with self._lock:
            self._set(np.array([x, self._hand[1], z]))

    def point_at_ray(self, origin: np.ndarray, direction: np.ndarray) -> bool:
        """Move the hand to where the ray meets the horizontal plane at the hand's height
        (clamped to the box). False when the ray misses the plane (parallel, or the plane
        is behind the camera)."""
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(direction, dtype=np.float64)
        with self._lock:
            if self.reach is None or abs(d[1]) < 1e-9:
                return False
            s = (self._hand[1] - o[1]) / d[1]
            if s <= 0.0 or not np.isfinite(s):
                return False
            p = o + s * d
            self._set(np.array([p[0], self._hand[1], p[2]]))
            return True

    def scroll(self, clicks: float) -> None:
        """Wheel: up (positive) raises the hand."""
        with self._lock:
            if self.reach is None:
                return
            dy = clicks * self.wheel_step * float(self.reach.half_extent[1])
            self._set(self._hand + np.array([0.0, dy, 0.0]))

    def drag_height(self, dy_pixels: float) -> None:
        """Right-button drag: dragging up (positive ``dy``) raises the hand."""
        with self._lock:
            if self.reach is None:
                return
            dy = dy_pixels * self.drag_gain * float(self.reach.half_extent[1])
            self._set(self._hand + np.array([0.0, dy, 0.0]))

    def centre(self) -> None:
        """Back to the middle of the box (the corner's rest anchor)."""
        with self._lock:
            if self.reach is not None:
                self._set(self.reach.centre)

    # --- what the window shows ------------------------------------------------------------
    def pull(self) -> tuple[np.ndarray, np.ndarray, float] | None:
        """(corner, hand, |F|) from the latest corner state, or None before the first one.
        The force is the coupling's ``K |h - c|`` with the hand as it is now."""
        with self._lock:
            if not self._has_corner:
                return None
            c = np.asarray(self._corner.position, dtype=np.float64)
            h = self._hand.copy()
            k = float(self._corner.stiffness)
        return c, h, k * float(np.linalg.norm(h - c))
