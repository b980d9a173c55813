"""The game's start on many grids: does a scene's trajectory converge in n?

The game starts every round the same way: the flat cloth at rest in the hands, the ball
0.4 m above it (the scene's start). ``trajectory`` runs that start through the public API
(``Cloth``, CPU float64 unless asked) and samples, every ``EVERY_S`` for ``DURATION_S``,
the ball's height and the cloth centre's height (the centre node, or the mean of the four
central nodes on an even grid: the bilinear value at the centre). Two grids' trajectories
differ by ``distance`` (the largest difference of any sample, m). ``events`` reads from the
same run the ball's first lowest point (height and time) and the first rebound (how far it
rises after it, before it falls again); ``grid.rest_state`` gives the static sag.

``python -m clothball.game.study.gamestart --scenes default,classic --sizes 13,25,49``
prints, per scene, every quantity on every grid, the differences between grids whose
spacing halves and the observed orders: the issue 42 table, reproducible.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
import tomllib
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from ..sim.cloth import Cloth, SimulationError
from ..sim.scene import Scene, available
from .grid import observed_order, rest_state, sized

DURATION_S = 1.5
EVERY_S = 0.05


@dataclass
class StartRun:
    """One grid's game start: the sampled trajectory and the quantities read from it."""

    scene: str
    n: int
    times_s: list[float] = field(default_factory=list)
    ball_y_m: list[float] = field(default_factory=list)
    centre_y_m: list[float] = field(default_factory=list)
    quantities: dict[str, float] = field(default_factory=dict)
    wall_s: float = math.nan

    def samples(self) -> np.ndarray:
        """(samples, 2): the ball's height and the centre's, m."""
        return np.column_stack([self.ball_y_m, self.centre_y_m])


def centre_height(x: np.ndarray) -> float:
    """The cloth's height at its centre: the centre node's, or the four central nodes' mean."""
    n = x.shape[0]
    lo, hi = (n - 1) // 2, n // 2 + 1
    return float(x[lo:hi, lo:hi, 1].mean())


def trajectory(scene: Scene, backend: str = "cpu", precision: str = "float64",
               threads: int | None = 1, duration_s: float = DURATION_S,
               every_s: float = EVERY_S, sag: bool = True) -> StartRun:
    """The game's start of ``scene`` at its n, sampled every ``every_s``; with ``sag`` the
    static sag of the hanging cloth (no ball) too."""
    run = StartRun(scene=scene.name, n=scene.n)
    t0 = time.perf_counter()
    cloth = Cloth(scene, backend=backend, precision=precision, threads=threads)
    frame_dt = cloth.frame_dt
    every = max(1, round(every_s / frame_dt))
    frames = round(duration_s / frame_dt)
    has_ball = "ball" in scene.effects
    ball_y: list[float] = []  # every frame, for the events
    for frame in range(1, frames + 1):
        cloth.step(1)
        by = float(cloth.ball()[0][1]) if has_ball else math.nan
        ball_y.append(by)
        if frame % every == 0:
            run.times_s.append(frame * frame_dt)
            run.ball_y_m.append(by)
            run.centre_y_m.append(centre_height(cloth.positions()))
    run.wall_s = time.perf_counter() - t0
    if has_ball:
        run.quantities.update(events(np.array(ball_y), frame_dt))
    if sag and "wind" not in scene.effects:  # a cloth in a steady wind never comes to rest
        try:
            _, run.quantities["sag_m"], run.quantities["hand_force_rest_n"] = rest_state(
                scene, backend, threads)
        except SimulationError:  # not at rest within grid.RELAX_MAX_S
            run.quantities.update(sag_m=math.nan, hand_force_rest_n=math.nan)
    return run


def _vertex(y: np.ndarray, k: int) -> tuple[float, float]:
    """The parabola through samples k - 1, k, k + 1: (its extreme value, its offset from k)."""
    if 0 < k < len(y) - 1:
        a, b, c = y[k - 1:k + 2]
        curve = a - 2 * b + c
        if curve != 0:
            return float(b - (a - c) ** 2 / (8 * curve)), float(0.5 * (a - c) / curve)
    return float(y[k]), 0.0


def events(ball_y: np.ndarray, frame_dt: float) -> dict[str, float]:
    """The ball's first lowest point (its height and time, a parabola through 3 frames)
    and its first rebound: how far it rises from there to the next highest point."""
    v = np.diff(ball_y)
    rising = np.nonzero(v > 0)[0]
    if len(rising) == 0:
        return {"lowest_y_m": math.nan, "lowest_s": math.nan, "rebound_m": math.nan}
    low = int(rising[0])  # the last frame before the ball first moves up
    lowest, shift = _vertex(ball_y, low)
    falling = np.nonzero(v[low:] < 0)[0]
    top = low + int(falling[0]) if len(falling) else len(ball_y) - 1
    highest, _ = _vertex(-ball_y, top)
    return {"lowest_y_m": lowest, "lowest_s": (low + 1 + shift) * frame_dt,
            "rebound_m": -highest - lowest}


def distance(a: StartRun, b: StartRun) -> float:
    """The largest difference between two grids' sampled trajectories, m."""
    sa, sb = a.samples(), b.samples()
    m = min(len(sa), len(sb))
    diff = np.abs(sa[:m] - sb[:m])
    return float(np.nanmax(diff)) if np.isfinite(diff).any() else math.nan


QUANTITIES = ("sag_m", "hand_force_rest_n", "lowest_y_m", "lowest_s", "rebound_m")


@dataclass
class Table:
    """A scene over grids: the trajectories' distances between grids whose spacing halves,
    each quantity's values, differences and observed orders."""

    scene: str
    ns: list[int]
    distances: dict[str, float]
    distance_orders: list[float]
    values: dict[str, list[float]]
    orders: dict[str, list[float]]
    walls_s: list[float]


def halving_pairs(ns: Sequence[int]) -> list[tuple[int, int]]:
    """Pairs (n, 2 n - 1) or (n, 2 n) among ``ns``: the spacing halves (odd n) or the
    intervals double (n - 1 to 2 n - 1 is exact; 24 to 48 is the issue's even ladder)."""
    s = set(ns)
    out = []
    for n in sorted(ns):
        for m in (2 * n - 1, 2 * n):
            if m in s:
                out.append((n, m))
    return out


def table(scene: Scene, ns: Sequence[int], runs: dict[int, StartRun]) -> Table:
    pairs = halving_pairs(ns)
    dist = {f"{a},{b}": distance(runs[a], runs[b]) for a, b in pairs}
    dvals = list(dist.values())
    dorders = [math.log2(x / y) if x > 0 and y > 0 else math.nan
               for x, y in zip(dvals, dvals[1:], strict=False)]
    values = {q: [runs[n].quantities.get(q, math.nan) for n in ns] for q in QUANTITIES}
    orders = {}
    for q, vals in values.items():
        by_n = dict(zip(ns, vals, strict=True))
        orders[q] = [observed_order(by_n[a], by_n[b], by_n[c])
                     for a, b in pairs for b2, c in pairs if b2 == b]
    return Table(scene.name, list(ns), dist, dorders, values, orders,
                 [runs[n].wall_s for n in ns])


@functools.cache
def _scene(name: str) -> Scene:
    return Scene.load(name)


def scene_changes(items: list[str]) -> dict[str, dict[str, object]]:
    """``SECTION.KEY=VALUE`` items (each value a TOML value) as ``Scene.with_changes`` takes
    them: the study's and the lab's ``--set``."""
    changes: dict[str, dict[str, object]] = {}
    for item in items:
        key, _, value = item.partition("=")
        section, _, name = key.partition(".")
        changes.setdefault(section, {})[name] = tomllib.loads(f"v = {value}")["v"]
    return changes


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m clothball.game.study.gamestart",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default=",".join(available()))
    ap.add_argument("--sizes", default="13,25,49")
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--precision", default="float64")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-sag", action="store_true")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="change a key of every scene (a TOML value), e.g. "
                    "coupling.grip_radius=0.04: a suspect switched on or off")
    ap.add_argument("--json", default="")
    args = ap.parse_args(argv)
    changes = scene_changes(args.set)
    ns = [int(x) for x in args.sizes.split(",")]
    out = []
    for name in args.scenes.split(","):
        base = _scene(name) if not name.endswith(".toml") else Scene.load(name)
        base = base.with_changes(changes) if changes else base
        runs = {}
        for n in ns:
            runs[n] = trajectory(sized(base, n), args.backend, args.precision, args.threads,
                                 sag=not args.no_sag)
            print(f"  {name} n={n}: {runs[n].wall_s:.1f} s", file=sys.stderr, flush=True)
        t = table(base, ns, runs)
        out.append(t)
        print(format_table(t))
        sys.stdout.flush()
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump([asdict(t) for t in out], f, indent=1)
    return 0


def _fmt(x: float, scale: float = 1.0, digits: int = 1) -> str:
    return "-" if not math.isfinite(x) else f"{x * scale:.{digits}f}"


def format_table(t: Table) -> str:
    lines = [f"scene {t.scene}: n = {', '.join(map(str, t.ns))}"]
    lines.append("  trajectory d (mm): " + ", ".join(
        f"d({k}) {_fmt(v, 1e3)}" for k, v in t.distances.items())
        + "   orders " + ", ".join(_fmt(o, digits=2) for o in t.distance_orders))
    units = {"sag_m": (1e3, "mm", 1), "hand_force_rest_n": (1.0, "N", 4),
             "lowest_y_m": (1e3, "mm", 1), "lowest_s": (1e3, "ms", 1),
             "rebound_m": (1e3, "mm", 1)}
    for q, vals in t.values.items():
        scale, unit, dig = units[q]
        lines.append(f"  {q:18s} ({unit}): " + ", ".join(_fmt(v, scale, dig) for v in vals)
                     + "   orders " + ", ".join(_fmt(o, digits=2) for o in t.orders[q]))
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
