"""The grid in the study: what a cloth's physics converges to as n grows, and how far a
grid (with its step) is from it.

One scene, many n: ``measure`` runs the Fig. 4 drop (the cloth at its exact static
equilibrium, the ball let go at the scene's start) and a free oscillation of the hanging
cloth, and reads quantities that mean the same on every grid (``QUANTITIES``): the static
sag and corner force (the cloth at rest, no ball), the ball's landing time, lowest point
and rebound, the ringing frequency of the corner force after the impact, and the hanging
cloth's first natural frequency (damping off). ``convergence`` says whether successive
differences shrink as the spacing halves and at what observed order;
``richardson`` extrapolates a reference from the finest grids, against which
``grid_study`` measures each (n, step) candidate's spatial plus temporal error and cost:
the Pareto front has n and the step together (``clothball accuracy --grid``,
``docs/accuracy.md``).

A scene in per-node units (the paper's ``damping``, ``ball.stiffness``) is another material
on every grid; ``per_node_twin`` gives a material scene that same per-node parameters, so
the two can be compared (``docs/scenes.md``: units).
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from ..sim.cloth import Cloth, SimulationError
from ..sim.oracle import node_contact_stiffness, node_damping
from ..sim.scene import Scene
from .accuracy import start_substeps
from .integrators_ref import centre_sag, with_effects

# name: (unit, what): every quantity a grid is measured by.
QUANTITIES: dict[str, tuple[str, str]] = {
    "sag_m": ("m", "static sag of the hanging cloth's centre (at rest, no ball)"),
    "corner_force_rest_n": ("N", "force on a hand at rest (no ball)"),
    "landing_s": ("s", "when the ball reaches the cloth at rest (between frames: interpolated)"),
    "lowest_y_m": ("m", "the ball's lowest centre height (a parabola through 3 frames)"),
    "lowest_s": ("s", "when the ball is lowest (the parabola's vertex)"),
    "rebound_m": ("m", "how far the ball rises after its lowest point"),
    "ring_hz": ("Hz", "dominant frequency of the corner force after landing"),
    "natural_hz": ("Hz", "first natural frequency of the hanging cloth (damping off)"),
}
KICK_M_S = 0.05  # peak speed of the first-mode-shaped kick that starts the free oscillation
MIN_HZ = 0.5  # frequencies below this are drift, not a mode
RING_MIN_HZ = 1.0  # the corner force settles to its new mean over about a second


def sized(scene: Scene, n: int) -> Scene:
    """The scene on an n x n grid."""
    return scene.with_changes({"cloth": {"n": n}})


def per_node_twin(scene: Scene) -> Scene:
    """The scene with each material value replaced by the per-node value it derives at the
    scene's n: the same cloth at this n, another one at every other n (as the paper's
    per-node parameters are)."""
    data = scene.to_dict()
    cloth, ball = data.setdefault("cloth", {}), data.setdefault("ball", {})
    if "damping_rate" in cloth:
        del cloth["damping_rate"]
        cloth["damping"] = node_damping(scene)
    if "stiffness_per_area" in ball:
        del ball["stiffness_per_area"]
        ball["stiffness"] = node_contact_stiffness(scene)
    return Scene(data, name=f"{scene.name} (per node at n = {scene.n})")


def dominant_hz(signal: Sequence[float], dt: float, min_hz: float = MIN_HZ) -> float:
    """The strongest frequency above ``min_hz`` of a signal sampled every dt (linear trend removed,
    Hann window, zero-padded 64x, the peak refined by a parabola through its 3 bins)."""
    x = np.asarray(signal, dtype=np.float64)
    if len(x) < 8 or not np.all(np.isfinite(x)):
        return math.nan
    t = np.arange(len(x))
    x = (x - np.polyval(np.polyfit(t, x, 1), t)) * np.hanning(len(x))  # trend out
    size = 64 * len(x)
    amp = np.abs(np.fft.rfft(x, size))
    freqs = np.fft.rfftfreq(size, dt)
    amp[freqs < min_hz] = 0.0
    k = int(np.argmax(amp))
    if k == 0 or k == len(amp) - 1 or amp[k] == 0.0:
        return math.nan
    a, b, c = np.log(amp[k - 1:k + 2] + 1e-300)
    shift = 0.5 * (a - c) / (a - 2 * b + c) if a - 2 * b + c != 0 else 0.0
    return float((k + shift) * (freqs[1] - freqs[0]))


@dataclass
class GridRun:
    """One grid's quantities (``QUANTITIES``), its step and what a simulated ms cost."""

    scene: str
    n: int
    substeps: int  # per frame; 0: automatic
    quantities: dict[str, float] = field(default_factory=dict)
    us_per_sim_ms: float = math.nan
    failed: str = ""


RELAX_RATE = 40.0  # 1/s: about critical for the hanging cloth's first modes (3-4 Hz)
RELAX_CHUNK_S = 0.25
RELAX_MAX_S = 20.0
RELAX_SPEED = 1e-7  # m/s: at rest when no node moves faster


def rest_state(scene: Scene, backend: str, threads: int | None) -> tuple[np.ndarray, float, float]:
    """(equilibrium positions, centre sag, |force on hand 0|) of the hanging cloth, no
    ball: the engine in float64 from the flat start, damped at ``RELAX_RATE`` (damping does
    not move an equilibrium) until no node is faster than ``RELAX_SPEED``. Newton's method
    (``static_equilibrium``) finds the same state, but in NumPy it is minutes at n = 49."""
    relax = with_effects(scene, ["ball", "damping"]).to_dict()
    relax["cloth"]["damping_rate"] = RELAX_RATE
    fx = list(relax["sim"]["effects"]) + ["damping"]
    relax["sim"].update(effects=fx, precision="float64")
    s = Scene(relax, name=scene.name)
    cloth = Cloth(s, backend=backend, precision="float64", threads=threads)
    chunk = max(1, round(RELAX_CHUNK_S / float(s["sim"]["frame_dt"])))
    for _ in range(round(RELAX_MAX_S / RELAX_CHUNK_S)):
        cloth.step(chunk)
        if float(np.abs(cloth.velocities()).max()) < RELAX_SPEED:
            break
    else:
        raise SimulationError(f"the hanging cloth did not come to rest in {RELAX_MAX_S} s")
    x = cloth.positions()
    force = float(np.linalg.norm(cloth.corner_forces()[0])) if "coupling" in s.effects else 0.0
    return x, centre_sag(scene, x), force


def _with_substeps(scene: Scene, substeps: int) -> Scene:
    return scene if substeps <= 0 else scene.with_changes(
        {"sim": {"substeps": substeps, "allow_unstable": False}})


def measure(
    scene: Scene,
    substeps: int = 0,
    backend: str = "cpu",
    precision: str = "float64",
    duration_s: float = 1.5,
    threads: int | None = None,
) -> GridRun:
    """Every quantity of ``QUANTITIES`` for ``scene`` (at its n), stepped with ``substeps``
    a frame (0: the scene's automatic substeps)."""
    run = GridRun(scene=scene.name, n=scene.n, substeps=substeps)
    q = run.quantities
    frame_dt = float(scene["sim"]["frame_dt"])
    frames = max(1, round(duration_s / frame_dt))
    try:
        x, q["sag_m"], q["corner_force_rest_n"] = rest_state(scene, backend, threads)
        if "ball" in scene.effects:
            _drop(scene, substeps, backend, precision, frames, threads, x, run)
        q["natural_hz"] = _natural_hz(scene, substeps, backend, precision, frames, threads, x)
    except SimulationError as e:
        run.failed = str(e)
    return run


def _drop(scene: Scene, substeps: int, backend: str, precision: str, frames: int,
          threads: int | None, x: np.ndarray, run: GridRun) -> None:
    """The Fig. 4 drop from the equilibrium ``x``: landing, lowest point, rebound, ring."""
    q = run.quantities
    ball = scene["ball"]
    radius = float(ball["radius"])
    cloth = Cloth(_with_substeps(scene, substeps), backend=backend, precision=precision,
                  threads=threads)
    cloth.set_state(x, np.zeros_like(x))
    cloth.set_ball(np.array(ball["position"], dtype=np.float64),
                   np.array(ball["velocity"], dtype=np.float64))
    frame_dt = float(scene["sim"]["frame_dt"])
    heights, force, walls = [], [], []
    landing = -1
    gap = float(np.min(np.linalg.norm(x - cloth.ball()[0], axis=-1))) - radius
    for frame in range(1, frames + 1):
        t0 = time.perf_counter()
        cloth.step(1)
        walls.append(time.perf_counter() - t0)
        bp = cloth.ball()[0]
        heights.append(float(bp[1]))
        force.append(float(np.linalg.norm(cloth.corner_forces()[0])))
        if landing < 0:
            # The gap to the cloth at rest (it is, until touched): the contact is stiff
            # enough to push the first node out again within the frame it enters, so the
            # moved cloth's gap can miss the landing. The ball falls nearly uniformly over
            # a frame: the crossing by linear interpolation (a frame, 1 ms, is more than
            # the grids differ by).
            was, gap = gap, float(np.min(np.linalg.norm(x - bp, axis=-1))) - radius
            if gap < 0:
                landing = frame
                crossed = frame - gap / (gap - was) if was > 0 else frame
                q["landing_s"] = crossed * frame_dt
    run.us_per_sim_ms = statistics.median(walls[5:] or walls) / frame_dt * 1e-3 * 1e6
    if landing < 0:
        q.update(landing_s=math.nan, lowest_y_m=math.nan, lowest_s=math.nan,
                 rebound_m=math.nan, ring_hz=math.nan)
        return
    after = np.array(heights[landing - 1:])
    low = int(np.argmin(after))
    lowest, shift = after[low], 0.0
    if 0 < low < len(after) - 1:  # the parabola through the lowest frame and its neighbours
        a, b, c = after[low - 1:low + 2]
        curve = a - 2 * b + c
        if curve > 0:
            shift = 0.5 * (a - c) / curve
            lowest = b - (a - c) ** 2 / (8 * curve)
    q["lowest_y_m"] = float(lowest)
    q["lowest_s"] = (landing + low + shift) * frame_dt
    q["rebound_m"] = float(after[low:].max() - lowest)
    q["ring_hz"] = dominant_hz(force[landing - 1:], frame_dt, RING_MIN_HZ)


def _natural_hz(scene: Scene, substeps: int, backend: str, precision: str, frames: int,
                threads: int | None, x: np.ndarray) -> float:
    """The hanging cloth, damping and ball off, from its equilibrium ``x`` kicked in the
    shape of its first mode (a half sine each way): the centre's dominant frequency."""
    free = with_effects(scene, ["damping", "ball"])
    cloth = Cloth(_with_substeps(free, substeps), backend=backend, precision=precision,
                  threads=threads)
    n = free.n
    s = np.sin(np.pi * np.arange(n) / (n - 1))
    vel = np.zeros_like(x)
    vel[..., 1] = -KICK_M_S * np.outer(s, s)
    cloth.set_state(x, vel)
    lo, hi = (n - 1) // 2, n // 2 + 1
    centre = []
    for _ in range(frames):
        cloth.step(1)
        centre.append(float(cloth.positions()[lo:hi, lo:hi, 1].mean()))
    return dominant_hz(centre, float(free["sim"]["frame_dt"]))


# --- convergence ------------------------------------------------------------------------
def spacing(n: int, size: float = 1.0) -> float:
    return size / (n - 1)


@dataclass
class Convergence:
    """A quantity over grids: its values, the differences between neighbouring grids, and
    the observed order from each three grids whose spacings halve (nan: not fitted)."""

    name: str
    ns: list[int]
    values: list[float]
    differences: list[float]
    orders: list[float]

    def shrinking(self) -> bool:
        """Whether each difference is smaller than the one before (successive grids)."""
        d = [abs(v) for v in self.differences]
        return all(b < a for a, b in zip(d, d[1:], strict=False))


def observed_order(coarse: float, mid: float, fine: float, ratio: float = 2.0) -> float:
    """The order p with which q(h) = q* + C h^p fits three grids of spacings r h, h, h / r."""
    d1, d2 = coarse - mid, mid - fine
    if d1 == 0.0 or d2 == 0.0 or d1 * d2 < 0.0:
        return math.nan
    return math.log(abs(d1) / abs(d2)) / math.log(ratio)


def convergence(runs: Sequence[GridRun], name: str) -> Convergence:
    """``name`` over the runs (in order of n): neighbouring differences, and the observed
    order from each triple (n_a, n_b, n_c) whose spacings halve."""
    runs = sorted(runs, key=lambda r: r.n)
    ns = [r.n for r in runs]
    values = [r.quantities.get(name, math.nan) for r in runs]
    diffs = [b - a for a, b in zip(values, values[1:], strict=False)]
    by_n = dict(zip(ns, values, strict=True))
    orders = []
    for n in ns:
        mid, fine = 2 * n - 1, 4 * n - 3  # the spacing halves: (n - 1) doubles
        if mid in by_n and fine in by_n:
            orders.append(observed_order(by_n[n], by_n[mid], by_n[fine]))
    return Convergence(name, ns, values, diffs, orders)


def richardson(coarse: float, fine: float, order: float, ratio: float = 2.0) -> float:
    """The extrapolated limit of q(h) = q* + C h^p from q(r h) and q(h)."""
    return fine + (fine - coarse) / (ratio**order - 1.0)


# --- the study: n and the step together ---------------------------------------------------
@dataclass
class GridStudy:
    """``grid_study``'s result: the reference (Richardson limit of each quantity from the
    reference grids), and every candidate's error against it and cost."""

    scene: str
    reference_ns: list[int]
    reference: dict[str, float]
    reference_orders: dict[str, float]
    rows: list[dict[str, Any]] = field(default_factory=list)
    runs: list[GridRun] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["runs"] = [asdict(r) for r in self.runs]
        return d


# The quantities the study's error sums (relative): frequencies, forces and lengths that
# any grid has; the timing ones are read from the same run.
ERROR_QUANTITIES = ("sag_m", "corner_force_rest_n", "lowest_y_m", "rebound_m",
                    "landing_s", "lowest_s", "ring_hz", "natural_hz")
DEFAULT_ORDER = 1.0  # where three reference grids give no order


def reference_limits(runs: Sequence[GridRun]) -> tuple[dict[str, float], dict[str, float]]:
    """Richardson limits of every quantity from the reference runs (spacings halving; the
    order observed from the three finest, else ``DEFAULT_ORDER``)."""
    runs = sorted(runs, key=lambda r: r.n)
    limits, orders = {}, {}
    for name in QUANTITIES:
        c = convergence(runs, name)
        p = c.orders[-1] if c.orders and math.isfinite(c.orders[-1]) else DEFAULT_ORDER
        p = min(max(p, 0.5), 4.0)  # a wild fit from noisy values must not blow up
        orders[name] = p
        limits[name] = richardson(c.values[-2], c.values[-1], p) if len(runs) >= 2 else math.nan
    return limits, orders


def relative_errors(got: dict[str, float], ref: dict[str, float],
                    names: Sequence[str] = ERROR_QUANTITIES) -> dict[str, float]:
    """Each quantity's relative error (a rebound's relative to itself plus 1 cm, so that a
    near-zero rebound stays finite; inf where the run lacks a value the reference has)."""
    out = {}
    for name in names:
        g, r = got.get(name, math.nan), ref.get(name, math.nan)
        if not math.isfinite(r):
            continue
        scale = abs(r) + (0.01 if name == "rebound_m" else 0.0)
        out[name] = abs(g - r) / max(scale, 1e-12) if math.isfinite(g) else math.inf
    return out


def relative_error(got: dict[str, float], ref: dict[str, float],
                   names: Sequence[str] = ERROR_QUANTITIES) -> float:
    """The largest of ``relative_errors``."""
    return max(relative_errors(got, ref, names).values(), default=0.0)


def grid_study(
    scene: Scene,
    sizes: Sequence[int],
    reference_sizes: Sequence[int],
    step_factors: Sequence[int] = (1, 2, 4),
    backend: str = "cpu",
    precision: str = "float64",
    duration_s: float = 1.5,
    threads: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> GridStudy:
    """Candidates (n in ``sizes``) x (substeps: the bound's, times each of ``step_factors``)
    against the Richardson limit of the reference grids (automatic substeps, float64)."""
    tick = progress or (lambda label: None)
    ref_runs = []
    for n in sorted(reference_sizes):
        r = measure(sized(scene, n), 0, backend, "float64", duration_s, threads)
        tick(f"reference n={n}")
        ref_runs.append(r)
    limits, orders = reference_limits(ref_runs)
    study = GridStudy(scene.name, sorted(reference_sizes), limits, orders, runs=list(ref_runs))
    for n in sizes:
        s = sized(scene, n)
        bound = start_substeps(s, "semi_implicit_euler", _impact_speed(s))
        for f in step_factors:
            r = measure(s, bound * f, backend, precision, duration_s, threads)
            tick(f"n={n} substeps={bound * f}")
            study.runs.append(r)
            study.rows.append({
                "n": n, "substeps": bound * f, "dt_us": float(s["sim"]["frame_dt"]) / (bound * f)
                * 1e6, "error": relative_error(r.quantities, limits),
                "errors": relative_errors(r.quantities, limits),
                "us_per_sim_ms": r.us_per_sim_ms, "failed": r.failed,
                **{k: r.quantities.get(k, math.nan) for k in QUANTITIES},
            })
    front = pareto([(row["us_per_sim_ms"], row["error"]) for row in study.rows])
    for i, row in enumerate(study.rows):
        row["pareto"] = i in front
    return study


def _impact_speed(scene: Scene) -> float:
    """The ball's speed in free fall to a quarter of the cloth's size below its rest height
    (deeper than it sags): what the substep bound must allow for."""
    g = float(np.linalg.norm(scene["sim"]["gravity"])) if "gravity" in scene.effects else 0.0
    ball = scene["ball"]
    drop = float(ball["position"][1]) - (scene["cloth"]["height"] - scene["cloth"]["size"] / 4)
    return math.sqrt(float(np.dot(ball["velocity"], ball["velocity"])) + 2 * g * max(drop, 0.0))


def pareto(points: Sequence[tuple[float, float]]) -> set[int]:
    """Indices of the points no other point beats in both cost and error."""
    return {i for i, (c, e) in enumerate(points)
            if not any((c2 <= c and e2 <= e) and (c2 < c or e2 < e)
                       for j, (c2, e2) in enumerate(points) if j != i)}


def table(study: GridStudy) -> str:
    """The study as text: the reference, then each candidate."""
    lines = [f"reference: Richardson limit from n = {', '.join(map(str, study.reference_ns))}"
             " (float64, automatic substeps)"]
    for name, (unit, what) in QUANTITIES.items():
        lines.append(f"  {name:20} {study.reference[name]:12.6g} {unit:3}  order "
                     f"{study.reference_orders[name]:.2f}  ({what})")
    lines.append("")
    names = list(ERROR_QUANTITIES)
    lines.append("relative error against the reference, each quantity, and the largest")
    lines.append(f"{'n':>4} {'subst':>6} {'dt us':>7} " + " ".join(
        f"{q[:9]:>9}" for q in names) + f" {'largest':>8} {'us/sim ms':>9}  pareto")
    for row in study.rows:
        errs = row["errors"]
        lines.append(f"{row['n']:>4} {row['substeps']:>6} {row['dt_us']:>7.2f} " + " ".join(
            f"{errs.get(q, math.nan):>9.2g}" for q in names)
            + f" {row['error']:>8.2g} {row['us_per_sim_ms']:>9.3g}  "
            f"{'*' if row['pareto'] else ''}{row['failed']}")
    return "\n".join(lines)
