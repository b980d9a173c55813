"""The simulation facade: a cloth stepped by the native CPU or CUDA backend.

``Cloth`` validates every argument (a bad one raises ``ValueError`` naming it and changes
nothing), converts between the documented array shapes and the native engine, and picks
the substep count from the stability bound unless the scene fixes it.
"""

from __future__ import annotations

import logging
import math
import warnings

import numpy as np

from ... import _native
from .config import effect_names, native_config
from .grip import CORNER_INDEX
from .scene import Scene, SceneError
from .stability import auto_substeps, stable_dt, substeps_for_speeds
from .threads import choose as choose_threads

log = logging.getLogger("clothball")

BACKENDS = ("auto", "cpu", "cuda")
CPU_MAX_N = 4096  # largest cloth the CPU backend is built and tested for (16.8 M nodes)
MAX_FRAMES_PER_CALL = 10_000_000
# The engines count one call's substeps in a 32-bit int: longer requests go in chunks.
MAX_SUBSTEPS_PER_CALL = 2**31 - 1


class SimulationError(RuntimeError):
    """The simulation state became non-finite; the cloth must be reset or dropped."""


class UnstableSceneWarning(UserWarning):
    """A scene fixes a substep beyond the stability bound and sets allow_unstable."""


def cuda_unavailable_reason() -> str:
    """Empty when the CUDA backend can run here, else why not."""
    return _native.cuda_unavailable_reason()


def rest_positions(scene: Scene) -> np.ndarray:
    """Node (i, j) rests at x = -size/2 + j L, y = height, z = -size/2 + i L."""
    n, size = scene.n, scene["cloth"]["size"]
    L = scene.rest_length
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    pos = np.empty((n, n, 3))
    pos[..., 0] = -size / 2 + j * L
    pos[..., 1] = scene["cloth"]["height"]
    pos[..., 2] = -size / 2 + i * L
    return pos


def corners_of(mesh: np.ndarray) -> np.ndarray:
    """The 4 corner rows of an (n, n, 3) array, in the documented corner order."""
    return np.stack([mesh[i, j] for i, j in CORNER_INDEX])


def _as_finite(name: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name}: expected numbers of shape {shape}: {e}") from None
    if arr.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: must be finite (got NaN or Inf)")
    return arr


def check_frames(frames: object) -> int:
    """The ``frames`` of a step call: a whole number in 1..MAX_FRAMES_PER_CALL, else a
    ``ValueError`` naming it."""
    if isinstance(frames, bool) or not isinstance(frames, int | np.integer):
        raise ValueError(f"frames: expected a whole number, got {frames!r}")
    if not 1 <= frames <= MAX_FRAMES_PER_CALL:
        raise ValueError(f"frames: must be in 1..{MAX_FRAMES_PER_CALL}, got {frames}")
    return int(frames)


def frame_chunk(remaining: int, substeps: int, fixed: bool, gusts: bool) -> int:
    """Frames for one engine call, of ``remaining``: one with gusts (the wind changes every
    frame); at most 10 with automatic substeps (they follow the ball's speed and are
    re-checked between calls); never more substeps than the engines' 32-bit counter."""
    if gusts:
        return 1
    chunk = remaining if fixed else min(remaining, 10)
    return min(chunk, max(1, MAX_SUBSTEPS_PER_CALL // substeps))


_NOTED: set[str] = set()  # the "auto" choices logged (resolve_backend)


def resolve_backend(scene: Scene, backend: str, precision: str | None
                    ) -> tuple[str, str, str]:
    """(backend, precision, note) for a cloth of ``scene``: ``"auto"`` is CUDA when a GPU is
    present, else the CPU (logged, with why); ``precision`` None is the scene's. Bad
    arguments raise ``ValueError`` naming the argument."""
    if not isinstance(scene, Scene):
        raise ValueError(f"scene: expected a Scene, got {type(scene).__name__}")
    if backend not in BACKENDS:
        raise ValueError(f"backend: must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if precision is None:
        precision = scene["sim"]["precision"]
    if precision not in ("float32", "float64"):
        raise ValueError(f"precision: must be 'float32' or 'float64', got {precision!r}")
    why_not = cuda_unavailable_reason()
    if backend == "auto":
        backend = "cuda" if not why_not else "cpu"
        note = "CUDA device found" if backend == "cuda" else f"using the CPU backend: {why_not}"
        if note not in _NOTED:  # once a process: every room and calibration asks again
            _NOTED.add(note)
            log.info("clothball backend: %s (%s)", backend, note)
    elif backend == "cuda" and why_not:
        raise ValueError(f"backend: 'cuda' requested but {why_not}")
    else:
        note = f"{backend} requested"
    if backend == "cpu" and scene.n > CPU_MAX_N:
        raise ValueError(
            f"scene: n = {scene.n} is larger than the CPU backend supports "
            f"(n <= {CPU_MAX_N}); use backend='cuda'"
        )
    return backend, precision, note


def wind_at(scene: Scene, t: float) -> np.ndarray:
    """The wind velocity at simulated time t (gusts: x (1 + a sin(2 pi t / T)))."""
    wind = scene["wind"]
    a, period = wind["gust_amplitude"], wind["gust_period"]
    return np.array(wind["velocity"], dtype=np.float64) * (
        1.0 + a * math.sin(2.0 * math.pi * t / period))


def check_fixed_dt(scene: Scene) -> None:
    """A scene's fixed substep count must keep dt within the stability bound, unless the
    scene allows it (then a warning)."""
    fixed = scene["sim"]["substeps"]
    dt = float(scene["sim"]["frame_dt"]) / fixed
    bound = stable_dt(scene)
    if dt <= bound:
        return
    need = auto_substeps(scene)
    msg = (
        f"sim.substeps = {fixed} gives dt = {dt:.3g} s, beyond the stability "
        f"bound {bound:.3g} s of this scene (use at least {need} substeps, or leave "
        f"sim.substeps out for automatic substeps)"
    )
    if not scene["sim"]["allow_unstable"]:
        raise SceneError(msg)
    warnings.warn(
        msg + "; accepted because sim.allow_unstable = true", UnstableSceneWarning, stacklevel=3
    )


class Cloth:
    """A cloth simulation of ``scene`` on the CPU or CUDA backend.

    ``backend="auto"`` picks CUDA when a GPU is present, else the CPU, and logs which
    (``backend_note`` says why). ``precision`` overrides the scene's ``sim.precision``.
    ``threads`` sets the CPU backend's threads (default: by the cloth's size and the cores
    free now, ``game.sim.threads``; ``self.threads`` says how many); a server that shares
    the cores with its network loop may want 1.
    Not thread-safe: one thread steps it at a time (stepping releases the GIL).
    """

    def __init__(
        self,
        scene: Scene,
        backend: str = "auto",
        precision: str | None = None,
        threads: int | None = None,
    ) -> None:
        backend, precision, self.backend_note = resolve_backend(scene, backend, precision)
        if threads is not None and (
            isinstance(threads, bool) or not isinstance(threads, int) or not 1 <= threads <= 1024
        ):
            raise ValueError(f"threads: must be a whole number in 1..1024, got {threads!r}")
        self.scene = scene
        self.backend = backend
        self.precision = precision
        self._fixed_substeps = scene["sim"]["substeps"]
        self._frame_dt = float(scene["sim"]["frame_dt"])
        if self._fixed_substeps is not None:
            check_fixed_dt(scene)
        # The CPU's threads: as asked, else by the nodes between two of their barriers
        # (a substep's) and the cores free now (``threads``); None on CUDA.
        self.threads = choose_threads(scene.n * scene.n, threads) if backend == "cpu" else None
        self._engine = _native.Engine(
            backend, precision == "float64", native_config(scene, self.threads or 0)
        )
        self._coupled = "coupling" in scene.effects
        self._has_ball = "ball" in scene.effects
        self._k = float(scene["coupling"]["stiffness"]) if self._coupled else 0.0
        self._gusts = "wind" in scene.effects and scene["wind"]["gust_amplitude"] > 0.0
        self.reset()

    def reset(self) -> None:
        """Back to the scene's start: cloth at rest, hands at the corners, ball placed."""
        rest = rest_positions(self.scene)
        self._engine.set_state(rest, np.zeros_like(rest))
        self._hips = corners_of(rest)
        self._engine.set_hips(self._hips)
        ball = self.scene["ball"]
        self._engine.set_ball(np.array([*ball["position"], *ball["velocity"]], dtype=np.float64))
        self.frame = 0
        self._apply_wind()
        self._refresh_substeps()

    def wind_at(self, t: float) -> np.ndarray:
        """The wind velocity at simulated time t (gusts: x (1 + a sin(2 pi t / T)))."""
        return wind_at(self.scene, t)

    def _apply_wind(self) -> None:
        self._engine.set_wind(self.wind_at(self.frame * self._frame_dt))

    @property
    def ball_contact_active(self) -> bool:
        """Whether the next substep computes ball contact: False while no node can reach
        the ball (it is off the cloth), when the kernels run compiled without contact.
        Always True with edge contact (ball.contact = "edges")."""
        return self._engine.ball_contact_on()

    @property
    def compiled_effects(self) -> frozenset[str]:
        """The effects the running kernels simulate: their compiled set (the costly
        effects) and the run-time ones (gravity, damping, coupling; docs/effects.md)."""
        return effect_names(self._engine.compiled_effects())

    @property
    def engine_path(self) -> str:
        """How the engine steps a frame: "cpu"; on CUDA "tiled" (the whole frame in one
        launch, the state on chip: large cloths), "substeps" (a launch a substep) or
        "node_a_thread" (the largest cloths); README.md, Building, says when each is taken."""
        return self._engine.path()

    # --- stepping -------------------------------------------------------------------------
    def _refresh_substeps(self) -> None:
        if self._fixed_substeps is not None:
            self._substeps = int(self._fixed_substeps)
        else:
            speed = float(np.linalg.norm(self._engine.ball()[3:])) if self._has_ball else 0.0
            self._substeps = int(substeps_for_speeds(self.scene, np.array([speed]))[0])

    @property
    def substeps(self) -> int:
        """Substeps per frame (chosen from the stability bound unless the scene fixes it)."""
        return self._substeps

    @property
    def dt(self) -> float:
        """Substep length in seconds: frame_dt / substeps."""
        return self._frame_dt / self._substeps

    @property
    def frame_dt(self) -> float:
        return self._frame_dt

    def step(self, frames: int = 1) -> None:
        """Advance ``frames`` frames of ``frame_dt`` each, ``substeps`` substeps a frame."""
        remaining = check_frames(frames)
        while remaining:
            chunk = frame_chunk(remaining, self._substeps, self._fixed_substeps is not None,
                                self._gusts)
            if self._gusts:
                self._apply_wind()
            self._engine.step(chunk, self._substeps, self.dt)
            self.frame += chunk
            remaining -= chunk
            self._check_finite()
            if self._fixed_substeps is None:
                self._refresh_substeps()

    def _check_finite(self) -> None:
        ball = self._engine.ball()
        if not (self._engine.state_finite() and np.all(np.isfinite(ball))):
            raise SimulationError(
                f"simulation state became non-finite by frame {self.frame} "
                f"(backend {self.backend}, {self.precision}, {self._substeps} substeps)"
            )

    # --- inputs ---------------------------------------------------------------------------
    def set_hips(self, h: object) -> None:
        """Hand positions (4, 3) in metres, corner order (0,0), (0,n-1), (n-1,n-1), (n-1,0)."""
        hips = _as_finite("h", h, (4, 3))
        self._engine.set_hips(hips)
        self._hips = hips

    def set_state(self, positions: object, velocities: object) -> None:
        """Replace every node's position and velocity, each (n, n, 3)."""
        n = self.scene.n
        pos = _as_finite("positions", positions, (n, n, 3))
        vel = _as_finite("velocities", velocities, (n, n, 3))
        self._engine.set_state(pos, vel)

    def set_ball(self, position: object, velocity: object = (0.0, 0.0, 0.0)) -> None:
        """Place the ball (centre, m) with a velocity (m/s)."""
        if not self._has_ball:
            raise ValueError("set_ball: this scene has no 'ball' effect")
        p = _as_finite("position", position, (3,))
        v = _as_finite("velocity", velocity, (3,))
        self._engine.set_ball(np.concatenate([p, v]))
        self._refresh_substeps()

    # --- outputs --------------------------------------------------------------------------
    def positions(self) -> np.ndarray:
        return self._engine.positions()

    def velocities(self) -> np.ndarray:
        return self._engine.velocities()

    def normals(self) -> np.ndarray:
        """Unit normals (n, n, 3) from the cross product of the grid tangents."""
        return self._engine.normals()

    def hips(self) -> np.ndarray:
        return self._hips.copy()

    def corners(self) -> tuple[np.ndarray, np.ndarray]:
        """Corner positions and velocities, each (4, 3): all that leaves the GPU per frame."""
        c = self._engine.corners()
        return c[:, :3].copy(), c[:, 3:].copy()

    def corner_forces(self) -> np.ndarray:
        """Force on each device (4, 3), N: -K (h - c) (eq. 7)."""
        if not self._coupled:
            return np.zeros((4, 3))
        c = self._engine.corners()[:, :3]
        return -self._k * (self._hips - c)

    def ball(self) -> tuple[np.ndarray, np.ndarray]:
        """Ball centre (m) and velocity (m/s)."""
        b = self._engine.ball()
        return b[:3].copy(), b[3:].copy()

    def __repr__(self) -> str:
        return (
            f"Cloth({self.scene.name!r}, n={self.scene.n}, backend={self.backend!r}, "
            f"precision={self.precision!r}, substeps={self.substeps})"
        )
