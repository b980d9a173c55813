"""What accuracy costs in time: error against a float64 reference, and wall time, for each
integrator, precision, substep size and grid size.

The study (``clothball accuracy`` runs it; ``docs/accuracy.md`` explains the results):

* **Trajectory error**, the paper's Fig. 4 scenario: the cloth hangs at rest from hands at
  its rest corners (its exact static equilibrium, from ``static_equilibrium``), the ball is
  let go at the scene's start position, and the run lasts ``duration`` seconds. Every
  ``sample_ms`` the node positions, and every frame the ball, are compared with a float64
  run of the same integrator whose step is 16 times smaller than the smallest step of the
  sweep. After contact the motion is chaotic (``decorrelation_time``: a 1e-10 m
  perturbation reaches 1e-4 m within a few hundred ms), so an error over the whole run
  saturates whatever the step. ``error_short_m`` is the RMS node distance over the samples
  up to a short window past the first contact (``short_window_end``: ``short_after_s``,
  and at most halfway from contact to decorrelation): there each integrator's error
  scales with its order, which ``orders`` fits. ``error_rms_m`` (all samples) and
  ``ball_error_m`` (the ball, every frame) cover the whole run.
* **Long-horizon quantities** (``quantities``), each against one long reference, velocity
  Verlet in float64 at its finest step / 16: the peak corner force after the first contact
  (the paper's Fig. 4b), the late-time means of the corner force and of the ball's height
  (the last ``LATE_FRACTION`` of the run) and the amplitude spectrum of the corner force
  after contact (what a haptic user feels).
* **Steady-state sag**: the hanging cloth's centre sag from Newton's method on F(x) = 0
  (``static_equilibrium``), and how it converges as the grid is refined
  (``sag_convergence``): the spatial error, which no time step removes. Every integrator
  here has that equilibrium as its fixed point (v = 0 with F(x) = 0 is a fixed point of each
  update, whatever dt), so time stepping cannot bias the steady state; what can is
  rounding. ``sag_error_m`` is how far the centre's sag is from Newton's after the cloth
  (no ball) is started at the float64 equilibrium and run for ``hold_s`` seconds in the
  precision under test. (Settling from a flat start would mostly measure how slowly the
  scene's light damping, c / m, dies away.)
* **Energy drift**: the Fig. 4 run with every damping switched off; the largest change of
  total mechanical energy over the run, relative to the energy the ball gains falling onto
  the cloth (``energy_drift``).
* **Cost**: wall time per simulated millisecond (``us_per_sim_ms``), the median over the
  trajectory run's frames (stepped one at a time, as the game's 1 kHz loop does) after a
  few warm-up frames, on the same machine in the same run.

Substep sizes: each integrator starts at its own bound (``stability.py``: the explicit
stability bound for semi-implicit Euler and velocity Verlet, the ball-tunnelling bound
capped at one substep per frame for implicit Euler) and halves. Implicit Euler runs with
the scene's CG settings; its reference solves CG to ``REFERENCE_CG_TOLERANCE``.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from ..sim.cloth import Cloth, SimulationError, corners_of, rest_positions
from ..sim.scene import INTEGRATORS as NATIVE_INTEGRATORS
from ..sim.scene import Scene
from ..sim.stability import auto_substeps
from .integrators_ref import (
    INTEGRATORS,
    ORDERS,
    IntegratingCloth,
    centre_sag,
    kinetic_energy,
    potential_energy,
    static_equilibrium,
    with_effects,
)

PRECISIONS = ("float32", "float64")
REFERENCE_FACTOR = 16  # the reference step is this many times smaller than the finest step
# Implicit Euler's reference: CG to this relative residual. Its steps are 16x smaller than
# the finest, where the system is nearly the mass matrix and CG needs few iterations.
REFERENCE_CG_TOLERANCE = 1e-10
REFERENCE_CG_ITERATIONS = 100


# --- simulations ----------------------------------------------------------------------------
class RefSim:
    """``IntegratingCloth`` (NumPy float64) behind the ``Cloth`` methods the study uses."""

    def __init__(self, scene: Scene, integrator: str, substeps: int) -> None:
        self.ref = IntegratingCloth(scene, integrator)
        self.substeps = substeps
        self.frame_dt = float(scene["sim"]["frame_dt"])

    def set_state(self, positions: np.ndarray, velocities: np.ndarray) -> None:
        self.ref.pos = np.array(positions, dtype=np.float64)
        self.ref.vel = np.array(velocities, dtype=np.float64)

    def set_ball(self, position: Sequence[float], velocity: Sequence[float]) -> None:
        self.ref.ball_pos = np.array(position, dtype=np.float64)
        self.ref.ball_vel = np.array(velocity, dtype=np.float64)

    def step(self, frames: int = 1) -> None:
        self.ref.step(frames, self.substeps)
        if not (np.all(np.isfinite(self.ref.pos)) and np.all(np.isfinite(self.ref.ball_pos))):
            raise SimulationError("reference simulation became non-finite")

    def positions(self) -> np.ndarray:
        return self.ref.pos.copy()

    def velocities(self) -> np.ndarray:
        return self.ref.vel.copy()

    def ball(self) -> tuple[np.ndarray, np.ndarray]:
        return self.ref.ball_pos.copy(), self.ref.ball_vel.copy()

    def corner_forces(self) -> np.ndarray:
        return self.ref.corner_forces()


def native_integrators() -> tuple[str, ...]:
    """Integrators the native engine (both backends) implements."""
    return tuple(NATIVE_INTEGRATORS)


def make_sim(
    scene: Scene, integrator: str, precision: str, substeps: int, backend: str,
    reference: bool = False, threads: int | None = None,
) -> tuple[Any, str]:
    """A simulation of ``scene`` with fixed substeps, and the engine that runs it.

    The native engine where it implements the integrator; else the NumPy reference
    (float64 only, and far slower: its timings are not the engine's). ``reference``: the
    study's reference run (implicit Euler then solves CG tightly). ``threads``: the CPU
    backend's threads (None: all cores)."""
    changes: dict[str, Any] = {"substeps": int(substeps)}
    if integrator != "semi_implicit_euler":
        changes["integrator"] = integrator
    if reference and integrator == "implicit_euler":
        changes["cg_tolerance"] = REFERENCE_CG_TOLERANCE
        changes["cg_max_iterations"] = REFERENCE_CG_ITERATIONS
    if integrator in native_integrators():
        sim = Cloth(scene.with_changes({"sim": changes}), backend=backend, precision=precision,
                    threads=threads)
        return sim, f"native-{sim.backend}"
    if precision != "float64":
        raise ValueError(f"{integrator} in {precision}: the native engine lacks it and the "
                         f"NumPy reference is float64 only")
    return RefSim(scene, integrator, substeps), "numpy"


# --- scenarios ----------------------------------------------------------------------------
def undamped(scene: Scene) -> Scene:
    """The scene with the cloth's and the ball's damping off (energy is then conserved)."""
    s = with_effects(scene, ["damping"])
    if "ball" in s.effects:
        s = s.with_changes({"ball": {"damping": 0.0}})
    return s


@dataclass
class Start:
    """The Fig. 4 start: the cloth at rest in equilibrium, the ball let go above it."""

    pos: np.ndarray
    ball_pos: np.ndarray
    ball_vel: np.ndarray
    hips: np.ndarray
    sag_m: float
    newton_iterations: int


def fig4_start(scene: Scene) -> Start:
    x, info = static_equilibrium(scene)
    ball = scene["ball"]
    return Start(
        pos=x,
        ball_pos=np.array(ball["position"], dtype=np.float64),
        ball_vel=np.array(ball["velocity"], dtype=np.float64),
        hips=corners_of(rest_positions(scene)),
        sag_m=centre_sag(scene, x),
        newton_iterations=int(info["iterations"]),
    )


def impact_speed(scene: Scene, start: Start) -> float:
    """Speed of the ball when it reaches the resting cloth's centre (free fall)."""
    g = float(np.linalg.norm(scene["sim"]["gravity"])) if "gravity" in scene.effects else 0.0
    top = scene["cloth"]["height"] - start.sag_m + scene["ball"]["radius"]
    drop = max(0.0, float(start.ball_pos[1]) - top)
    return math.sqrt(float(start.ball_vel @ start.ball_vel) + 2.0 * g * drop)


def drop_energy(scene: Scene, start: Start) -> float:
    """The drift's yardstick: the ball's kinetic energy on reaching the resting cloth plus
    the weight times its radius (what sinking into the cloth releases); never zero."""
    g = float(np.linalg.norm(scene["sim"]["gravity"])) if "gravity" in scene.effects else 0.0
    m, r = scene["ball"]["mass"], scene["ball"]["radius"]
    return 0.5 * m * impact_speed(scene, start) ** 2 + m * max(g, 1e-9) * r


def start_substeps(scene: Scene, integrator: str, ball_speed: float) -> int:
    """Substeps per frame at the largest step the integrator may take in this scene (its
    own bound, ``stability.py``), at the ball's impact speed."""
    return auto_substeps(scene.with_changes({"sim": {"integrator": integrator}}), ball_speed)


@dataclass
class Trajectory:
    """A run of the Fig. 4 scenario: the ball and the hand force every frame, the mesh (and
    the energy) every ``sample_frames`` frames, the wall time of every frame."""

    times_s: list[float] = field(default_factory=list)  # every frame
    ball: list[np.ndarray] = field(default_factory=list)
    corner_force: list[float] = field(default_factory=list)  # |F| on hand 0, N
    sample_times_s: list[float] = field(default_factory=list)  # every sample
    pos: list[np.ndarray] = field(default_factory=list)
    energy: list[float] = field(default_factory=list)
    frame_s: list[float] = field(default_factory=list)  # wall time of each frame
    failed: str = ""


def run_trajectory(
    sim: Any,
    scene: Scene,
    start: Start,
    duration_s: float,
    sample_frames: int,
    energy: bool = False,
) -> Trajectory:
    """Step frame by frame, as the game's 1 kHz loop does, timing each frame."""
    sim.set_state(start.pos, np.zeros_like(start.pos))
    if "ball" in scene.effects:
        sim.set_ball(start.ball_pos, start.ball_vel)
    frame_dt = float(scene["sim"]["frame_dt"])
    frames = max(1, round(duration_s / frame_dt))
    out = Trajectory()

    def record(frame: int) -> None:
        bp, bv = sim.ball()
        out.times_s.append(frame * frame_dt)
        out.ball.append(bp)
        out.corner_force.append(float(np.linalg.norm(sim.corner_forces()[0])))
        if frame % sample_frames == 0 or frame == frames:
            pos = sim.positions()
            out.sample_times_s.append(frame * frame_dt)
            out.pos.append(pos)
            if energy:
                vel = sim.velocities()
                out.energy.append(kinetic_energy(scene, vel, bv)
                                  + potential_energy(scene, pos, bp, start.hips))

    record(0)
    for frame in range(1, frames + 1):
        t0 = time.perf_counter()
        try:
            sim.step(1)
        except SimulationError as e:
            out.failed = str(e)
            break
        out.frame_s.append(time.perf_counter() - t0)
        record(frame)
    return out


def trajectory_errors(run: Trajectory, ref: Trajectory) -> tuple[float, float]:
    """(RMS node distance over the mesh samples, RMS ball distance over the frames), t > 0."""
    if run.failed:
        return math.inf, math.inf
    k = min(len(run.pos), len(ref.pos))
    node = [np.sum((run.pos[i] - ref.pos[i]) ** 2, axis=-1).mean() for i in range(1, k)]
    kb = min(len(run.ball), len(ref.ball))
    ball = [float(np.sum((run.ball[i] - ref.ball[i]) ** 2)) for i in range(1, kb)]
    if not node or not (np.all(np.isfinite(node)) and np.all(np.isfinite(ball))):
        return math.inf, math.inf
    return math.sqrt(float(np.mean(node))), math.sqrt(float(np.mean(ball)))


def contact_time(run: Trajectory, radius: float) -> float:
    """First mesh sample at which a node is inside the ball (inf: never)."""
    if not run.times_s:
        return math.inf
    frame_dt = run.times_s[1] - run.times_s[0] if len(run.times_s) > 1 else 1.0
    for t, pos in zip(run.sample_times_s, run.pos, strict=True):
        b = run.ball[min(len(run.ball) - 1, round(t / frame_dt))]
        if float(np.min(np.linalg.norm(pos - b, axis=-1))) < radius:
            return t
    return math.inf


def short_window_end(contact_s: float, after_s: float, duration_s: float,
                     decorrelation_s: float = math.inf) -> float:
    """End of the short-horizon window: ``after_s`` past the first contact, but at most
    halfway from contact to decorrelation (so a perturbation is still far below the
    threshold: the error is the integrator's, not chaos's), and within the run. Without
    contact the whole run."""
    if not math.isfinite(contact_s):
        return duration_s
    end = contact_s + after_s
    if math.isfinite(decorrelation_s) and decorrelation_s > contact_s:
        end = min(end, 0.5 * (contact_s + decorrelation_s))
    return min(end, duration_s)


def short_error(run: Trajectory, ref: Trajectory, end_s: float) -> float:
    """RMS node distance over the mesh samples with 0 < t <= ``end_s``."""
    if run.failed:
        return math.inf
    k = min(len(run.pos), len(ref.pos))
    sq = [np.sum((run.pos[i] - ref.pos[i]) ** 2, axis=-1).mean() for i in range(1, k)
          if run.sample_times_s[i] <= end_s + 1e-12]
    if not sq or not np.all(np.isfinite(sq)):
        return math.inf
    return math.sqrt(float(np.mean(sq)))


# The long-horizon quantities' reference integrator (float64, REFERENCE_FACTOR x finer).
LONG_REFERENCE = "velocity_verlet"
# The late-time means are over this last fraction of the run. In the classic scene the ball
# still rebounds at 1 s (it settles over many seconds): these are late-time means of the
# run, compared with the reference's, not rest values.
LATE_FRACTION = 0.2


@dataclass
class Quantities:
    """What a haptic user and a physicist read off a run, far less sensitive to chaos than a
    trajectory: the peak of the
    corner force after the first contact, the late-time mean of the corner force and of the
    ball's height (the last ``LATE_FRACTION`` of the run), and the amplitude spectrum of
    the corner force from the first contact on (Hann window)."""

    peak_force_n: float
    late_force_n: float
    ball_late_m: float
    freqs_hz: np.ndarray
    spectrum: np.ndarray


def quantities(run: Trajectory, contact_s: float) -> Quantities | None:
    """The run's long-horizon quantities; None where it failed or never made contact."""
    if run.failed or not math.isfinite(contact_s) or len(run.times_s) < 8:
        return None
    t = np.asarray(run.times_s)
    f = np.asarray(run.corner_force)
    y = np.asarray([b[1] for b in run.ball])
    hit = t >= contact_s
    tail = t >= t[-1] - LATE_FRACTION * (t[-1] - t[0])
    sig = f[hit] - f[hit].mean()
    if len(sig) < 4:
        return None
    amp = np.abs(np.fft.rfft(sig * np.hanning(len(sig))))
    freqs = np.fft.rfftfreq(len(sig), float(t[1] - t[0]))
    return Quantities(float(f[hit].max()), float(f[tail].mean()), float(y[tail].mean()),
                      freqs, amp)


def quantity_errors(got: Quantities | None, ref: Quantities | None) -> dict[str, float]:
    """Errors of ``got`` against ``ref``: relative for the forces and the spectrum (L2 of the
    amplitude difference over the reference's), metres for the ball's late-time height."""
    keys = ("peak_force_err", "late_force_err", "ball_late_err_m", "spectrum_err")
    if got is None or ref is None:
        return dict.fromkeys(keys, math.inf if ref is not None else math.nan)
    k = min(len(got.spectrum), len(ref.spectrum))
    spec = float(np.linalg.norm(got.spectrum[:k] - ref.spectrum[:k])
                 / max(np.linalg.norm(ref.spectrum[:k]), 1e-300))
    return {
        "peak_force_err": abs(got.peak_force_n - ref.peak_force_n) / ref.peak_force_n,
        "late_force_err": abs(got.late_force_n - ref.late_force_n)
        / ref.late_force_n,
        "ball_late_err_m": abs(got.ball_late_m - ref.ball_late_m),
        "spectrum_err": spec,
    }


def long_summary(q: Quantities | None, integrator: str, substeps: int,
                 contact_s: float) -> dict[str, Any]:
    """The long reference's quantities, for the table, the JSON and the spectrum plot."""
    out: dict[str, Any] = {"integrator": integrator, "substeps": substeps,
                           "contact_s": contact_s}
    if q is None:
        return out
    peak = int(np.argmax(q.spectrum[1:])) + 1 if len(q.spectrum) > 1 else 0
    out.update(peak_force_n=q.peak_force_n, late_force_n=q.late_force_n,
               ball_late_m=q.ball_late_m, dominant_hz=float(q.freqs_hz[peak]),
               spectrum={"freqs_hz": q.freqs_hz.tolist(), "amplitude": q.spectrum.tolist()})
    return out


def energy_drift(run: Trajectory, scale: float) -> float:
    if run.failed or not run.energy or not np.all(np.isfinite(run.energy)):
        return math.inf
    e = np.asarray(run.energy)
    return float(np.max(np.abs(e - e[0])) / scale)


def cost_us_per_sim_ms(run: Trajectory, frame_dt: float, warmup: int = 5) -> float:
    """Median wall time per simulated ms over the frames after the first few (warm-up)."""
    frames = run.frame_s[warmup:] or run.frame_s
    if not frames:
        return math.nan
    return statistics.median(frames) / (frame_dt * 1e3) * 1e6


def steady_sag(sim: Any, scene: Scene, start: np.ndarray, hold_s: float) -> float:
    """The cloth (no ball) started at the exact equilibrium ``start`` and run ``hold_s``:
    its centre sag then. Each integrator's fixed point is F(x) = 0, so this shows where
    rounding (and any instability) leaves the steady state."""
    sim.set_state(start, np.zeros_like(start))
    frame_dt = float(scene["sim"]["frame_dt"])
    sim.step(max(1, round(hold_s / frame_dt)))
    return centre_sag(scene, sim.positions())


@dataclass
class Decorrelation:
    """Two runs from starts ``perturb_m`` apart: when their separation reaches
    ``threshold_m`` (inf: not within the horizon) and the exponential growth rate fitted
    to the separation (1/s) between the perturbation's size and the threshold."""

    time_s: float
    rate_per_s: float
    perturb_m: float
    threshold_m: float
    horizon_s: float


def decorrelation_time(
    scene: Scene, integrator: str, precision: str, substeps: int, backend: str = "cpu",
    perturb_m: float = 1e-10, threshold_m: float = 1e-4, horizon_s: float = 1.0,
    threads: int | None = None,
) -> Decorrelation:
    """The Lyapunov-style horizon past which trajectories of this scene cannot be compared:
    every node of one run is moved ``perturb_m`` along x and both are stepped together."""
    start = fig4_start(scene)
    sims = [make_sim(scene, integrator, precision, substeps, backend, threads=threads)[0]
            for _ in range(2)]
    shifted = start.pos.copy()
    shifted[..., 0] += perturb_m
    for sim, pos in zip(sims, (start.pos, shifted), strict=True):
        sim.set_state(pos, np.zeros_like(pos))
        if "ball" in scene.effects:
            sim.set_ball(start.ball_pos, start.ball_vel)
    frame_dt = float(scene["sim"]["frame_dt"])
    ts, seps, hit = [], [], math.inf
    for frame in range(1, max(1, round(horizon_s / frame_dt)) + 1):
        for sim in sims:
            sim.step(1)
        sep = float(np.max(np.abs(sims[0].positions() - sims[1].positions())))
        ts.append(frame * frame_dt)
        seps.append(sep)
        if sep >= threshold_m:
            hit = frame * frame_dt
            break
    # Growth fitted where the separation is well above the seed and below saturation.
    pts = [(t, e) for t, e in zip(ts, seps, strict=True) if 10 * perturb_m < e < threshold_m]
    rate = (float(np.polyfit([p[0] for p in pts], np.log([p[1] for p in pts]), 1)[0])
            if len(pts) >= MIN_FIT_POINTS else math.nan)
    return Decorrelation(hit, rate, perturb_m, threshold_m, horizon_s)


# --- the sweep ------------------------------------------------------------------------------
@dataclass
class Row:
    integrator: str
    precision: str
    n: int
    substeps: int
    dt_us: float
    level: int  # 0: the largest step; k: 2^-k of it
    error_short_m: float  # RMS node error from the start to the end of the short window
    error_rms_m: float  # over the whole run: saturates once the run decorrelates
    ball_error_m: float
    sag_error_m: float
    energy_drift: float
    us_per_sim_ms: float
    engine: str
    reference_substeps: int
    short_window_s: float = math.nan  # where the short window ends (simulated time)
    # Long-horizon quantities against the long reference (``Study.long_reference``).
    peak_force_err: float = math.nan  # relative
    late_force_err: float = math.nan  # relative
    ball_late_err_m: float = math.nan
    spectrum_err: float = math.nan  # relative L2 of the corner force's amplitude spectrum
    note: str = ""


@dataclass
class Study:
    rows: list[Row]
    sag_convergence: list[dict[str, float]]
    fig4: dict[str, Any]
    meta: dict[str, Any]
    decorrelation: dict[str, Any] | None = None  # asdict(Decorrelation) and its case
    long_reference: dict[int, dict[str, Any]] = field(default_factory=dict)  # per n

    def to_json(self) -> dict[str, Any]:
        def clean(v: Any) -> Any:
            if isinstance(v, float) and not math.isfinite(v):
                return None
            return v

        rows = [{k: clean(v) for k, v in asdict(r).items()} for r in self.rows]
        fits = [{"integrator": i, "precision": p, "n": n, "metric": "error_short_m",
                 "order": o if isinstance(o, float) else None,
                 "textbook_order": ORDERS.get(i),
                 "note": order_note(i, o)}
                for (i, p, n), o in orders(self.rows).items()]
        dec = ({k: clean(v) for k, v in self.decorrelation.items()}
               if self.decorrelation else None)
        longs = [{k: clean(v) for k, v in d.items() if k != "spectrum"}
                 for d in self.long_reference.values()]
        return {"rows": rows, "summary": {"fitted_order": fits, "decorrelation": dec,
                                          "long_reference": longs,
                                          "spatial_vs_temporal": spatial_vs_temporal(self)},
                "sag_convergence": self.sag_convergence, "fig4": self.fig4, "meta": self.meta}


@dataclass
class Plan:
    scene: Scene
    sizes: Sequence[int]
    integrators: Sequence[str]
    precisions: Sequence[str]
    levels: int = 4
    duration_s: float = 1.0
    sample_ms: int = 5
    backend: str = "cpu"
    sag_sizes: Sequence[int] = (9, 17, 33)
    energy: bool = True
    sag: bool = True
    hold_s: float = 1.0
    decorrelation: bool = False  # also measure the decorrelation time (needs the ball)
    short_after_s: float = 0.02  # the short window ends this long after the first contact
    threads: int | None = None  # the CPU backend's threads (None: all cores)

    def cases(self) -> int:
        per_n = len(self.integrators) * (len(self.precisions) * self.levels + 1)
        dec = 1 if self.decorrelation and "ball" in self.scene.effects else 0
        return len(self.sizes) * per_n + dec


def sized(scene: Scene, n: int) -> Scene:
    return scene.with_changes({"cloth": {"n": n}})


def run_study(plan: Plan, progress: Callable[[str], None] | None = None) -> Study:
    """Run the whole sweep; ``progress`` is called once per finished run with a label."""
    tick = progress or (lambda label: None)
    rows: list[Row] = []
    fig4: dict[str, Any] = {}
    sample_frames = max(1, round(plan.sample_ms * 1e-3 / float(plan.scene["sim"]["frame_dt"])))
    frame_dt = float(plan.scene["sim"]["frame_dt"])
    sag_conv: dict[int, dict[str, float]] = {}
    dec = None
    if plan.decorrelation and "ball" in plan.scene.effects:
        # The native engine's own case, at the smallest n and the integrator's largest step;
        # measured first: the short window must end before it.
        integ = next((i for i in plan.integrators if i in native_integrators()),
                     plan.integrators[0])
        prec = "float64" if "float64" in plan.precisions else plan.precisions[0]
        scene = sized(plan.scene, plan.sizes[0])
        sub = start_substeps(scene, integ, impact_speed(scene, fig4_start(scene)))
        d = decorrelation_time(scene, integ, prec, sub, plan.backend,
                               horizon_s=max(plan.duration_s, 1.0), threads=plan.threads)
        dec = {**asdict(d), "integrator": integ, "precision": prec, "n": plan.sizes[0],
               "substeps": sub}
        tick(f"n={plan.sizes[0]} decorrelation time")
    dec_s = dec["time_s"] if dec else math.inf
    long_ref: dict[int, dict[str, Any]] = {}
    for n in plan.sizes:
        scene = sized(plan.scene, n)
        start = fig4_start(scene)
        sag_conv[n] = {"n": n, "sag_m": start.sag_m, "newton_iterations": start.newton_iterations}
        speed = impact_speed(scene, start)
        e_scale = drop_energy(scene, start) if "ball" in scene.effects else 1.0
        quiet = with_effects(scene, ["ball"])
        eq_quiet = start.pos  # static_equilibrium leaves the ball out
        radius = float(scene["ball"]["radius"]) if "ball" in scene.effects else 0.0
        first = {integ: start_substeps(scene, integ, speed) for integ in plan.integrators}
        refs: dict[str, tuple[Trajectory, int]] = {}
        for integ in plan.integrators:
            s_ref = first[integ] * 2 ** (plan.levels - 1) * REFERENCE_FACTOR
            ref_sim, _ = make_sim(scene, integ, "float64", s_ref, plan.backend, reference=True,
                                  threads=plan.threads)
            refs[integ] = (run_trajectory(ref_sim, scene, start, plan.duration_s,
                                          sample_frames), s_ref)
            del ref_sim
            tick(f"n={n} {integ} reference ({s_ref} substeps/frame)")
        # The long-horizon quantities are physical, so every integrator is held to one
        # reference: the most accurate, velocity Verlet's (else each its own).
        long_integ = LONG_REFERENCE if LONG_REFERENCE in refs else None
        for integ in plan.integrators:
            ref, s_ref = refs[integ]
            lref, ls_ref = refs[long_integ or integ]
            contact = contact_time(ref, radius)
            short_end = short_window_end(contact, plan.short_after_s, plan.duration_s, dec_s)
            lcontact = contact_time(lref, radius)
            lq = quantities(lref, lcontact)
            if integ == (long_integ or plan.integrators[0]):
                long_ref[n] = {"n": n, **long_summary(lq, long_integ or integ, ls_ref, lcontact)}
            s0 = first[integ]
            for prec in plan.precisions:
                for level in range(plan.levels):
                    s = s0 * 2**level
                    label = f"n={n} {integ} {prec} {s} substeps/frame"
                    try:
                        sim, engine = make_sim(scene, integ, prec, s, plan.backend,
                                               threads=plan.threads)
                    except ValueError as e:
                        rows.append(Row(integ, prec, n, s, frame_dt / s * 1e6, level, math.nan,
                                        math.nan, math.nan, math.nan, math.nan, math.nan, "-",
                                        s_ref, short_end, note=str(e)))
                        tick(label)
                        continue
                    run = run_trajectory(sim, scene, start, plan.duration_s, sample_frames)
                    err, berr = trajectory_errors(run, ref)
                    err_short = short_error(run, ref, short_end)
                    qerr = quantity_errors(quantities(run, contact_time(run, radius)), lq)
                    cost = cost_us_per_sim_ms(run, frame_dt)
                    del sim
                    drift = math.nan
                    if plan.energy:
                        esim, _ = make_sim(undamped(scene), integ, prec, s, plan.backend,
                                           threads=plan.threads)
                        erun = run_trajectory(esim, undamped(scene), start, plan.duration_s,
                                              sample_frames, energy=True)
                        drift = energy_drift(erun, e_scale)
                        del esim
                    sag_err = math.nan
                    note = run.failed
                    if plan.sag and level == 0:
                        ssim, _ = make_sim(quiet, integ, prec, s, plan.backend,
                                           threads=plan.threads)
                        try:
                            sag = steady_sag(ssim, quiet, eq_quiet, plan.hold_s)
                            sag_err = abs(sag - centre_sag(quiet, eq_quiet))
                        except SimulationError as e:
                            note = note or str(e)
                        del ssim
                    rows.append(Row(integ, prec, n, s, frame_dt / s * 1e6, level, err_short, err,
                                    berr, sag_err, drift, cost, engine, s_ref, short_end,
                                    note=note, **qerr))
                    if n == plan.sizes[0] and level == 0:
                        fig4[f"{integ} {prec} {s} substeps"] = {
                            "t_s": run.times_s, "ball_y_m": [float(b[1]) for b in run.ball],
                            "corner_force_n": run.corner_force}
                    tick(label)
            if n == plan.sizes[0]:
                fig4[f"{integ} reference float64 {s_ref} substeps"] = {
                    "t_s": ref.times_s, "ball_y_m": [float(b[1]) for b in ref.ball],
                    "corner_force_n": ref.corner_force}
    if plan.sag:
        for n in plan.sag_sizes:
            if n not in sag_conv:
                sc = with_effects(sized(plan.scene, n), ["ball"])
                x, info = static_equilibrium(sc)
                sag_conv[n] = {"n": n, "sag_m": centre_sag(sc, x),
                               "newton_iterations": int(info["iterations"])}
                tick(f"n={n} Newton equilibrium")
    conv = [sag_conv[k] for k in sorted(sag_conv)]
    for a, b in zip(conv, conv[1:], strict=False):
        b["change_from_previous_m"] = b["sag_m"] - a["sag_m"]
    meta = {
        "scene": plan.scene.name,
        "effects": sorted(plan.scene.effects),
        "backend": plan.backend,
        "duration_s": plan.duration_s,
        "sample_ms": plan.sample_ms,
        "levels": plan.levels,
        "reference_factor": REFERENCE_FACTOR,
        "hold_s": plan.hold_s,
        "threads": plan.threads,
    }
    meta["late_fraction"] = LATE_FRACTION
    meta["short_after_s"] = plan.short_after_s
    return Study(rows, conv, fig4, meta, dec, long_ref)


# --- analysis -------------------------------------------------------------------------------
def spatial_vs_temporal(study: Study) -> list[dict[str, Any]]:
    """Per n: the spatial error of the static sag (its distance from the sag on the finest
    grid computed, so a lower bound of the true spatial error) beside the temporal errors of
    the ball's late-time mean height at the largest and the smallest step of each float64
    curve."""
    conv = {int(c["n"]): c["sag_m"] for c in study.sag_convergence}
    if not conv:
        return []
    finest = max(conv)
    out = []
    for n in sorted({r.n for r in study.rows}):
        entry: dict[str, Any] = {"n": n, "finest_n": finest,
                                 "spatial_sag_m": abs(conv[n] - conv[finest])
                                 if n in conv and n != finest else None}
        for integ in dict.fromkeys(r.integrator for r in study.rows):
            rs = sorted((r for r in study.rows if (r.n, r.integrator, r.precision)
                         == (n, integ, "float64") and math.isfinite(r.ball_late_err_m)),
                        key=lambda r: r.level)
            if rs:
                entry[f"temporal_ball_late_m {integ}"] = [rs[0].ball_late_err_m,
                                                          rs[-1].ball_late_err_m]
        out.append(entry)
    return out


def fitted_order(dts: Sequence[float], errors: Sequence[float]) -> float:
    """Least-squares slope of log(error) against log(dt)."""
    x, y = np.log(np.asarray(dts)), np.log(np.asarray(errors))
    return float(np.polyfit(x, y, 1)[0])


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both cost and error (lower is
    better), sorted by cost."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        c, e = points[i]
        if math.isfinite(c) and math.isfinite(e) and e < best:
            front.append(i)
            best = e
    return front


# Below this an error is round-off, not truncation: a slope through it means nothing.
ROUNDOFF_M = 1e-9
# A slope needs at least this many points above round-off to show an asymptotic range.
MIN_FIT_POINTS = 3


# Local slopes (between neighbouring steps) that agree within this span are one asymptotic
# range: coarser, the error is pre-asymptotic; finer, rounding flattens it.
SLOPE_SPAN = 0.3


def asymptotic_range(dts: Sequence[float], errors: Sequence[float]) -> list[int]:
    """Indices (sorted by dt) of the longest run of neighbouring steps whose local slopes
    log(e_i / e_j) / log(dt_i / dt_j) all lie within ``SLOPE_SPAN`` of each other."""
    idx = sorted(range(len(dts)), key=lambda i: dts[i])
    if len(idx) < 2:
        return idx
    slopes = [math.log(errors[b] / errors[a]) / math.log(dts[b] / dts[a])
              for a, b in zip(idx, idx[1:], strict=False)]
    best = (0, 1)  # slopes[lo:hi]
    for lo in range(len(slopes)):
        for hi in range(lo + 1, len(slopes) + 1):
            seg = slopes[lo:hi]
            if max(seg) - min(seg) <= SLOPE_SPAN and hi - lo > best[1] - best[0]:
                best = (lo, hi)
    return idx[best[0]:best[1] + 1]


def orders(rows: Sequence[Row], metric: str = "error_short_m",
           ) -> dict[tuple[str, str, int], float | str]:
    """Fitted order of ``metric`` against dt for each (integrator, precision, n) curve, or,
    where no order can honestly be fitted, a short reason why (printed instead of a
    number): fewer than ``MIN_FIT_POINTS`` errors above round-off, or no asymptotic range
    of that many points."""
    out: dict[tuple[str, str, int], float | str] = {}
    keys = sorted({(r.integrator, r.precision, r.n) for r in rows})
    for key in keys:
        pts = [(r.dt_us, getattr(r, metric)) for r in rows
               if (r.integrator, r.precision, r.n) == key
               and math.isfinite(getattr(r, metric)) and getattr(r, metric) >= ROUNDOFF_M]
        if len(pts) < MIN_FIT_POINTS:
            out[key] = (f"no order: {len(pts)} point(s) above round-off ({ROUNDOFF_M:g} m), "
                        f"{MIN_FIT_POINTS} needed")
            continue
        keep = asymptotic_range([p[0] for p in pts], [p[1] for p in pts])
        if len(keep) < MIN_FIT_POINTS:
            out[key] = (f"no order: local slopes disagree (no {MIN_FIT_POINTS} steps in an "
                        f"asymptotic range)")
            continue
        out[key] = fitted_order([pts[i][0] for i in keep], [pts[i][1] for i in keep])
    return out


# A fitted order this close to the textbook one shows the asymptotic range.
ORDER_TOLERANCE = 0.25


def order_note(integrator: str, order: float | str) -> str:
    """What a fitted order says: why there is none, or whether the steps were in the
    integrator's asymptotic range (the textbook order, within ``ORDER_TOLERANCE``)."""
    if not isinstance(order, float):
        return order
    book = ORDERS.get(integrator)
    if book is None:
        return ""
    if abs(order - book) <= ORDER_TOLERANCE:
        return f"textbook order {book}"
    if order < book:
        return (f"pre-asymptotic (textbook order {book}): the steps are too large for the "
                f"error to scale as dt^{book}")
    return f"above the textbook order {book}: error cancellation, not a trend"


def table(study: Study) -> str:
    def f(v: float, w: int = 10) -> str:
        return f"{'-':>{w}}" if not math.isfinite(v) else f"{v:>{w}.3g}"

    key = f"{'integrator':<20} {'prec':<7} {'n':>4} {'subst':>5} {'dt us':>8} "
    head = key + f"{'short m':>10} {'us/sim ms':>10}  engine"
    lines = ["short-horizon error and cost", head, "-" * len(head)]
    for r in study.rows:
        lines.append(
            f"{r.integrator:<20} {r.precision:<7} {r.n:>4} {r.substeps:>5} {r.dt_us:>8.2f} "
            f"{f(r.error_short_m)} {f(r.us_per_sim_ms)}  {r.engine}"
            f"{'  ' + r.note if r.note else ''}")
    head2 = key + (f"{'peak F':>9} {'late F':>9} {'ball late':>10} {'spectrum':>9} "
                   f"{'E drift':>9} {'sag m':>9} {'run err m':>9}")
    lines += ["", "long horizon (forces and spectrum relative; ball height and sag in m)",
              head2, "-" * len(head2)]
    for r in study.rows:
        lines.append(
            f"{r.integrator:<20} {r.precision:<7} {r.n:>4} {r.substeps:>5} {r.dt_us:>8.2f} "
            f"{f(r.peak_force_err, 9)} {f(r.late_force_err, 9)} {f(r.ball_late_err_m)} "
            f"{f(r.spectrum_err, 9)} {f(r.energy_drift, 9)} {f(r.sag_error_m, 9)} "
            f"{f(r.error_rms_m, 9)}")
    ends = sorted({round(r.short_window_s, 3) for r in study.rows
                   if math.isfinite(r.short_window_s)})
    lines.append("")
    lines.append("short: RMS node error up to " + (", ".join(f"{e:g}" for e in ends) or "-")
                 + " s (the first contact plus a short window, before decorrelation)")
    for d in study.long_reference.values():
        if "peak_force_n" in d:
            lines.append(
                f"long reference n={d['n']}: {d['integrator']} float64 {d['substeps']} "
                f"substeps/frame: peak corner force {d['peak_force_n']:.3g} N, late "
                f"{d['late_force_n']:.3g} N, ball late height {d['ball_late_m']:.4g} m, "
                f"spectrum peak {d['dominant_hz']:.3g} Hz (late: mean over the last "
                f"{LATE_FRACTION:.0%} of the run)")
    lines.append("run err: RMS node error over the whole run (saturates once it decorrelates)")
    lines.append("fitted short-horizon order (slope of log error vs log dt):")
    for (integ, prec, n), p in orders(study.rows).items():
        shown = f"{p:5.2f}  {order_note(integ, p)}" if isinstance(p, float) else p
        lines.append(f"  {integ:<20} {prec:<7} n={n:<4} {shown}")
    if study.decorrelation:
        d = study.decorrelation
        when = (f"{d['time_s'] * 1e3:.0f} ms" if math.isfinite(d["time_s"])
                else f"not within {d['horizon_s']:g} s")
        lines.append("")
        lines.append(f"decorrelation: {d['perturb_m']:g} m grows to {d['threshold_m']:g} m "
                     f"in {when} (growth {d['rate_per_s']:.3g}/s; {d['integrator']} "
                     f"{d['precision']} n={d['n']}): trajectories past this cannot be compared")
    svt = spatial_vs_temporal(study)
    if svt:
        lines.append("")
        lines.append("spatial against temporal error (m): the sag's change to the finest n "
                     "beside the ball's late height error at the largest / smallest step")
        for e in svt:
            sp = e["spatial_sag_m"]
            parts = [f"  n={e['n']:<4} spatial {f(sp) if sp is not None else '-':>10}"]
            for k, (hi, lo) in ((k, v) for k, v in e.items() if k.startswith("temporal")):
                parts.append(f"{k.split()[1]} {hi:.2g} / {lo:.2g}")
            lines.append("   ".join(parts))
    if study.sag_convergence:
        lines.append("")
        lines.append("static sag (Newton) against grid size:")
        for c in study.sag_convergence:
            ch = c.get("change_from_previous_m")
            extra = f"   change {ch * 1e3:+.2f} mm" if ch is not None else ""
            lines.append(f"  n={int(c['n']):<4} sag {c['sag_m'] * 1e3:8.2f} mm{extra}")
    return "\n".join(lines)


# --- plots ----------------------------------------------------------------------------------
STYLE = {"semi_implicit_euler": ("tab:blue", "o"), "velocity_verlet": ("tab:green", "s"),
         "implicit_euler": ("tab:red", "^")}


PLOT_HINT = "plots need matplotlib: pip install 'clothball[study]'"


def pyplot() -> Any:
    """matplotlib.pyplot on the file-only backend; ``RuntimeError(PLOT_HINT)`` without it
    (an optional extra: the game does not need it)."""
    try:
        import matplotlib  # noqa: PLC0415
    except ImportError:
        raise RuntimeError(PLOT_HINT) from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    return plt


# The plot's panels: (Row field, panel title, y label).
METRICS = (
    ("error_short_m", "short-horizon trajectory error", "RMS node error (m)"),
    ("peak_force_err", "peak corner force after impact", "relative error"),
    ("late_force_err", "corner force, late-time mean", "relative error"),
    ("ball_late_err_m", "ball height, late-time mean", "error (m)"),
    ("spectrum_err", "corner-force spectrum", "relative L2 error"),
    ("energy_drift", "energy drift, undamped", "max |dE| / impact energy"),
)


def plot_error_vs_cost(study: Study, path: str) -> None:
    """One panel per metric and grid size (two rows of three a size): error against wall
    time per simulated ms, log-log, a curve per integrator and precision (the step halves
    along it), and that panel's Pareto front circled."""
    plt = pyplot()
    from matplotlib.ticker import NullFormatter  # noqa: PLC0415

    sizes = sorted({r.n for r in study.rows})
    cols = 3
    per = -(-len(METRICS) // cols)  # rows of panels a size
    fig, axes = plt.subplots(per * len(sizes), cols, squeeze=False,
                             figsize=(5.4 * cols, 4.0 * per * len(sizes) + 0.8))
    handles: dict[str, Any] = {}
    for k, n in enumerate(sizes):
        for i, (attr, title, what) in enumerate(METRICS):
            ax = axes[k * per + i // cols][i % cols]
            pts = []
            for integ in INTEGRATORS:
                for prec in PRECISIONS:
                    rs = [r for r in study.rows
                          if (r.integrator, r.precision, r.n) == (integ, prec, n)
                          and math.isfinite(getattr(r, attr)) and getattr(r, attr) > 0
                          and math.isfinite(r.us_per_sim_ms)]
                    if not rs:
                        continue
                    color, marker = STYLE.get(integ, ("k", "x"))
                    (line,) = ax.plot([r.us_per_sim_ms for r in rs],
                                      [getattr(r, attr) for r in rs],
                                      color=color, marker=marker,
                                      linestyle="-" if prec == "float64" else "--",
                                      markerfacecolor=color if prec == "float64" else "none")
                    handles.setdefault(f"{integ} {prec}", line)
                    pts += [(r.us_per_sim_ms, getattr(r, attr)) for r in rs]
            front = pareto_front(pts)
            if front:
                fx = [pts[i][0] for i in front]
                fy = [pts[i][1] for i in front]
                ax.step(fx, fy, where="post", color="k", linewidth=1, alpha=0.6)
                handles.setdefault("Pareto front", ax.scatter(
                    fx, fy, s=150, facecolors="none", edgecolors="k", linewidths=1.4, zorder=5))
            if pts:
                ax.set_xscale("log")
                ax.set_yscale("log")
                ax.xaxis.set_minor_formatter(NullFormatter())  # they overlap
            else:
                ax.text(0.5, 0.5, "not measured", ha="center", va="center",
                        transform=ax.transAxes)
            ax.set_xlabel("wall time per simulated ms (us)")
            ax.set_ylabel(what)
            ax.set_title(f"{title}, n = {n}", fontsize=10)
            ax.grid(True, which="both", alpha=0.3)
    for ax in axes.flat[len(sizes) * per * cols:]:
        ax.set_visible(False)
    fig.legend(list(handles.values()), list(handles.keys()), loc="lower center",
               ncol=min(4, max(1, len(handles))), fontsize=9)
    fig.suptitle(f"Error against cost ({study.meta.get('backend')}, "
                 f"{study.meta.get('scene')}): the step halves along each curve", fontsize=12)
    fig.tight_layout(rect=(0, 0.8 / fig.get_figheight(), 1, 0.98))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_fig4(study: Study, path: str) -> None:
    plt = pyplot()

    fig, (a, b, c) = plt.subplots(3, 1, figsize=(8, 10))
    for label, d in study.fig4.items():
        integ = label.split()[0]
        color, _ = STYLE.get(integ, ("k", "x"))
        ref = "reference" in label
        kw = {"color": "k" if ref else color, "linewidth": 2.2 if ref else 1.0,
              "linestyle": "-" if ref or "float64" in label else "--", "alpha": 0.8}
        if ref and integ != "velocity_verlet" and any(
                "velocity_verlet reference" in k for k in study.fig4):
            continue  # one reference curve is enough: they agree to plotting accuracy
        a.plot(d["t_s"], d["ball_y_m"], label=label, **kw)
        b.plot(d["t_s"], d["corner_force_n"], label=label, **kw)
    a.set_ylabel("ball height y (m)")
    a.set_title("Fig. 4 (a): ball dropped on the resting cloth")
    b.set_ylabel("|force| on hand 0 (N)")
    b.set_xlabel("time (s)")
    b.set_title("Fig. 4 (b): force on the haptic device at a corner")
    a.legend(fontsize=7)
    for d in study.long_reference.values():
        if "spectrum" in d:
            c.semilogy(d["spectrum"]["freqs_hz"], d["spectrum"]["amplitude"],
                       label=f"n = {d['n']}, {d['integrator']} float64 {d['substeps']} substeps")
    c.set_xlabel("frequency (Hz)")
    c.set_ylabel("|FFT| (N, Hann window, unnormalised)")
    c.set_title("corner force spectrum after the first contact (the long reference)")
    if c.lines:
        c.legend(fontsize=7)
    for ax in (a, b, c):
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
