"""``ClothBatch``: many cloths of one scene stepped by one call, for a server that runs many
rooms. Every slot is the same simulation as a lone ``Cloth`` of the scene (the same native
code; on the CPU a slot is bit for bit a ``Cloth`` with ``threads=1``), and a frame for all
slots costs one call in (``set_hips_all``), one step and one call out (``corners_all``).

Slots share the substep count: with automatic substeps the batch takes the largest any
occupied slot needs (a fast ball needs more). A slot whose state turns non-finite is
reported by ``step`` and reset (or freed, ``on_failure="remove"``) alone; the others step
on.
"""

from __future__ import annotations

import logging
from typing import Literal

import numpy as np

from ... import _native
from .cloth import (
    _as_finite,
    check_fixed_dt,
    check_frames,
    corners_of,
    frame_chunk,
    resolve_backend,
    rest_positions,
    wind_at,
)
from .config import native_config
from .scene import Scene
from .stability import auto_substeps, substeps_for_speeds
from .threads import choose as choose_threads

log = logging.getLogger("clothball.sim")

MAX_CAPACITY = 65_536


class ClothBatch:
    """Up to ``capacity`` cloths of ``scene`` (same n, effect set, precision, substeps).

    ``add()`` takes a free slot (its cloth starts as ``Cloth.reset()`` leaves one) and
    ``remove(slot)`` frees it; neither touches the other slots. ``step(frames)`` advances
    every occupied slot and returns the slots that failed (non-finite state) in that call.
    Not thread-safe: one thread calls it at a time (stepping releases the GIL).
    """

    def __init__(self, scene: Scene, capacity: int, backend: str = "auto",
                 precision: str | None = None,
                 on_failure: Literal["reset", "remove"] = "reset",
                 threads: int | None = None) -> None:
        backend, precision, self.backend_note = resolve_backend(scene, backend, precision)
        if isinstance(capacity, bool) or not isinstance(capacity, int | np.integer) or not (
                1 <= capacity <= MAX_CAPACITY):
            raise ValueError(f"capacity: must be a whole number in 1..{MAX_CAPACITY}, "
                             f"got {capacity!r}")
        if on_failure not in ("reset", "remove"):
            raise ValueError(f"on_failure: must be 'reset' or 'remove', got {on_failure!r}")
        self.scene = scene
        self.backend = backend
        self.precision = precision
        self.capacity = int(capacity)
        self.on_failure = on_failure
        self._fixed_substeps = scene["sim"]["substeps"]
        if self._fixed_substeps is not None:
            check_fixed_dt(scene)
        self._frame_dt = float(scene["sim"]["frame_dt"])
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int)
                                    or threads < 1):
            raise ValueError(f"threads: must be a whole number >= 1 or None, got {threads!r}")
        # CPU: the slots are shared among `threads` threads (None: by the slots' nodes and
        # the cores free now, ``game.sim.threads``); a slot is one thread's work.
        self.threads = choose_threads(self.capacity * scene.n * scene.n, threads) \
            if backend == "cpu" else None
        self._engine = _native.BatchEngine(backend, precision == "float64",
                                           native_config(scene), self.capacity,
                                           self.threads or 0)
        self._coupled = "coupling" in scene.effects
        self._has_ball = "ball" in scene.effects
        self._k = float(scene["coupling"]["stiffness"]) if self._coupled else 0.0
        self._gusts = "wind" in scene.effects and scene["wind"]["gust_amplitude"] > 0.0
        self._rest = rest_positions(scene)
        self._hips = np.zeros((self.capacity, 4, 3))
        self._frames = np.zeros(self.capacity, dtype=np.int64)  # frames since each reset
        self._used = np.zeros(self.capacity, dtype=bool)
        self._active = np.ones(self.capacity, dtype=bool)  # False: kept, not stepped
        self._slot_substeps = np.ones(self.capacity, dtype=np.int64)
        self._corners: np.ndarray | None = None  # (capacity, 4, 6), as of the last step
        self._balls: np.ndarray | None = None
        self.failures = 0  # slots reset or removed for a non-finite state, in all

    # --- slots ----------------------------------------------------------------------------
    def add(self) -> int:
        """A free slot, its cloth at the scene's start. ``ValueError`` when all are taken."""
        free = np.flatnonzero(~self._used)
        if free.size == 0:
            raise ValueError(f"add: all {self.capacity} slots are taken; remove one first")
        slot = int(free[0])
        self._engine.open(slot)
        self._used[slot] = True
        self._active[slot] = True
        self.reset(slot)
        return slot

    def remove(self, slot: int) -> None:
        """Free a slot (its memory too); the other slots are not touched."""
        self._check(slot)
        self._engine.close(slot)
        self._used[slot] = False
        self._corners = self._balls = None

    def set_active(self, slot: int, active: bool) -> None:
        """Pause (False) or resume (True) a slot: a paused slot keeps its state and frame
        count but is not stepped and costs no compute (a room nobody is in sleeps)."""
        slot = self._check(slot)
        self._engine.set_active(slot, bool(active))
        self._active[slot] = bool(active)

    def active(self, slot: int) -> bool:
        return bool(self._active[self._check(slot)])

    def slots(self) -> list[int]:
        """The occupied slots, in order."""
        return [int(s) for s in np.flatnonzero(self._used)]

    def reset(self, slot: int) -> None:
        """Back to the scene's start, as ``Cloth.reset``."""
        self._check(slot)
        e = self._engine
        e.set_state(slot, self._rest, np.zeros_like(self._rest))
        self._hips[slot] = corners_of(self._rest)
        e.set_hips(slot, self._hips[slot])
        ball = self.scene["ball"]
        e.set_ball(slot, np.array([*ball["position"], *ball["velocity"]], dtype=np.float64))
        self._frames[slot] = 0
        e.set_wind(slot, wind_at(self.scene, 0.0))
        self._refresh_substeps(slot)
        self._corners = self._balls = None

    def _check(self, slot: object) -> int:
        if isinstance(slot, bool) or not isinstance(slot, int | np.integer):
            raise ValueError(f"slot: expected a whole number, got {slot!r}")
        if not 0 <= slot < self.capacity or not self._used[slot]:
            raise ValueError(f"slot: {slot} is not an occupied slot (occupied: "
                             f"{self.slots()})")
        return int(slot)

    # --- stepping -------------------------------------------------------------------------
    def _refresh_substeps(self, slot: int) -> None:
        if self._fixed_substeps is not None:
            self._slot_substeps[slot] = int(self._fixed_substeps)
        else:
            speed = (float(np.linalg.norm(self._engine.ball(slot)[3:]))
                     if self._has_ball else 0.0)
            self._slot_substeps[slot] = auto_substeps(self.scene, speed)

    @property
    def substeps(self) -> int:
        """Substeps per frame for every slot: the largest any occupied, active slot needs."""
        live = self._used & self._active
        if not live.any():
            return int(self._fixed_substeps or 1)
        return int(self._slot_substeps[live].max())

    @property
    def native_engine(self) -> _native.BatchEngine:
        """The native batch, for a native driver that steps it without Python (the server's
        frame loop, ``_native.FrameLoop``). While one runs, this facade's calls are made
        only under the driver's lock, and its frame counts and substeps go stale."""
        return self._engine

    @property
    def dt(self) -> float:
        return self._frame_dt / self.substeps

    @property
    def frame_dt(self) -> float:
        return self._frame_dt

    def step(self, frames: int = 1) -> list[int]:
        """Advance every occupied, active slot ``frames`` frames. Returns the slots whose
        state turned non-finite (reset or removed, as ``on_failure`` says); the others step
        on."""
        remaining = check_frames(frames)
        failed: list[int] = []
        while remaining and (self._used & self._active).any():
            substeps = self.substeps
            # As Cloth (the same chunks, so a slot is bit for bit a lone cloth).
            chunk = frame_chunk(remaining, substeps, self._fixed_substeps is not None,
                                self._gusts)
            if self._gusts:
                t = self._frames * self._frame_dt
                self._engine.set_wind_all(np.stack([wind_at(self.scene, x) for x in t]))
            finite = self._engine.step(chunk, substeps, self._frame_dt / substeps)
            self._frames[self._used & self._active] += chunk
            remaining -= chunk
            for slot in np.flatnonzero(self._used & ~finite):
                failed.append(int(slot))
                self._fail(int(slot), substeps)
            self._corners = self._balls = None
            live = self._used & self._active
            if self._fixed_substeps is None and self._has_ball and live.any():
                # Every slot's need from one read of all balls (not a call per slot).
                speeds = np.linalg.norm(self._outputs()[1][live, 3:], axis=1)
                self._slot_substeps[live] = substeps_for_speeds(self.scene, speeds)
        return failed

    def _fail(self, slot: int, substeps: int) -> None:
        self.failures += 1
        log.warning("batch slot %d: state became non-finite by frame %d (backend %s, %s, "
                    "%d substeps); %s", slot, self._frames[slot], self.backend,
                    self.precision, substeps,
                    "reset" if self.on_failure == "reset" else "removed")
        if self.on_failure == "reset":
            self.reset(slot)
        else:
            self.remove(slot)

    # --- inputs ---------------------------------------------------------------------------
    def set_hips(self, slot: int, h: object) -> None:
        """One slot's hand positions (4, 3), metres, in the corner order of ``Cloth``."""
        slot = self._check(slot)
        hips = _as_finite("h", h, (4, 3))
        self._engine.set_hips(slot, hips)
        self._hips[slot] = hips

    def set_hips_all(self, h: object) -> None:
        """Every slot's hands at once, (capacity, 4, 3); rows of free slots are ignored."""
        hips = _as_finite("h", h, (self.capacity, 4, 3))
        self._engine.set_hips_all(hips)
        self._hips[self._used] = hips[self._used]

    def set_ball(self, slot: int, position: object,
                 velocity: object = (0.0, 0.0, 0.0)) -> None:
        slot = self._check(slot)
        if not self._has_ball:
            raise ValueError("set_ball: this scene has no 'ball' effect")
        p = _as_finite("position", position, (3,))
        v = _as_finite("velocity", velocity, (3,))
        self._engine.set_ball(slot, np.concatenate([p, v]))
        self._refresh_substeps(slot)
        self._balls = None

    def set_state(self, slot: int, positions: object, velocities: object) -> None:
        slot = self._check(slot)
        n = self.scene.n
        pos = _as_finite("positions", positions, (n, n, 3))
        vel = _as_finite("velocities", velocities, (n, n, 3))
        self._engine.set_state(slot, pos, vel)
        self._corners = None

    # --- outputs --------------------------------------------------------------------------
    def _outputs(self) -> tuple[np.ndarray, np.ndarray]:
        if self._corners is None or self._balls is None:
            self._corners, self._balls = self._engine.corners_all()
        return self._corners, self._balls

    def corners_all(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every slot at once: corner positions and velocities (capacity, 4, 3) each, and
        the balls (capacity, 6: position, velocity); free slots read 0."""
        c, b = self._outputs()
        return c[:, :, :3].copy(), c[:, :, 3:].copy(), b.copy()

    def corners(self, slot: int) -> tuple[np.ndarray, np.ndarray]:
        slot = self._check(slot)
        c = self._outputs()[0][slot]
        return c[:, :3].copy(), c[:, 3:].copy()

    def corner_forces(self, slot: int) -> np.ndarray:
        """Force on each of the slot's devices (4, 3), N: -K (h - c) (eq. 7)."""
        slot = self._check(slot)
        if not self._coupled:
            return np.zeros((4, 3))
        return -self._k * (self._hips[slot] - self._outputs()[0][slot][:, :3])

    def ball(self, slot: int) -> tuple[np.ndarray, np.ndarray]:
        slot = self._check(slot)
        b = self._outputs()[1][slot]
        return b[:3].copy(), b[3:].copy()

    def hips(self, slot: int) -> np.ndarray:
        return self._hips[self._check(slot)].copy()

    def positions(self, slot: int) -> np.ndarray:
        return self._engine.positions(self._check(slot))

    def gather_positions(self, slots: list[int]) -> np.ndarray:
        """The positions of several slots, (len(slots), n, n, 3), in one transfer (CUDA: one
        gather copy; the server's meshes)."""
        return self._engine.gather_positions([self._check(s) for s in slots])

    def velocities(self, slot: int) -> np.ndarray:
        return self._engine.velocities(self._check(slot))

    def normals(self, slot: int) -> np.ndarray:
        return self._engine.normals(self._check(slot))

    def frame(self, slot: int) -> int:
        """Frames the slot has stepped since it was added or last reset."""
        return int(self._frames[self._check(slot)])

    def __repr__(self) -> str:
        return (f"ClothBatch({self.scene.name!r}, n={self.scene.n}, {len(self.slots())}/"
                f"{self.capacity} slots, backend={self.backend!r}, "
                f"precision={self.precision!r}, substeps={self.substeps})")
