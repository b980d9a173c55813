"""What an implicit Euler substep costs against the CG iterations it uses.

``python -m clothball.game.study.cg_cost --backend cuda --json cg.json`` steps the Fig. 4
scene (the cloth at its static equilibrium, the ball let go) to just after the impact,
then times frames of one substep each:

* **forced**: ``cg_tolerance = 0`` and ``cg_max_iterations = k``, so every substep runs
  exactly k iterations (the cost of k iterations);
* **converged**: ``cg_max_iterations`` at its default (200) and a tolerance from loose to
  tight; the iterations CG needs for it are counted by the float64 NumPy reference
  (``IntegratingCloth``) over the same frames from the same state.

Where CG stops on the device when converged, a converged substep costs about what a forced
one of the same iteration count does; where all capped iterations are launched, every
converged substep costs about the forced 200. ``--unroll 1,4,8`` repeats the CUDA cases
with that many CG iterations captured in each turn of the device-side loop
(``CLOTHBALL_CG_UNROLL``; each turn costs a launch of its body, and the iterations after
CG stopped within a turn return at once).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import sys
import time
from collections.abc import Iterator
from typing import Any

from ..sim.cloth import Cloth
from ..sim.scene import Scene
from .accuracy import fig4_start, sized
from .integrators_ref import IntegratingCloth

FORCED = (1, 5, 10, 20, 50, 100, 200)
TOLERANCES = (1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-8)
UNROLL_ENV = "CLOTHBALL_CG_UNROLL"
SETTLE_S = 0.45  # the classic ball reaches the cloth at ~0.37 s


def _cloth(scene: Scene, backend: str, precision: str, tol: float, cap: int) -> Cloth:
    sim = {"integrator": "implicit_euler", "substeps": 1, "cg_tolerance": tol,
           "cg_max_iterations": cap}
    return Cloth(scene.with_changes({"sim": sim}), backend=backend, precision=precision)


def measure(n: int, backend: str, precisions: list[str], frames: int,
            unrolls: list[int | None] | None = None) -> list[dict[str, Any]]:
    scene = sized(Scene.load("classic"), n)
    start = fig4_start(scene)
    # The state just after the impact, from the default settings, shared by every case.
    warm = _cloth(scene, backend, "float64", 1e-5, 200)
    warm.set_state(start.pos, 0 * start.pos)
    warm.set_ball(start.ball_pos, start.ball_vel)
    warm.step(round(SETTLE_S / float(scene["sim"]["frame_dt"])))
    pos, vel = warm.positions(), warm.velocities()
    ball = warm.ball()
    out = []
    cases = [(0.0, k) for k in FORCED] + [(t, 200) for t in TOLERANCES]
    used: dict[float, float] = {}  # iterations a substep needs, per tolerance
    for tol, cap in cases:
        if tol > 0:
            ref = IntegratingCloth(scene, "implicit_euler", cg_tol=tol, cg_max_iter=cap)
            ref.pos, ref.vel = pos.copy(), vel.copy()
            ref.ball_pos, ref.ball_vel = ball[0].copy(), ball[1].copy()
            ref.step(frames, 1)
            used[tol] = ref.cg_iterations / frames
    for unroll in unrolls or [None]:
        for precision in precisions:
            for tol, cap in cases:
                with _unroll(unroll):
                    us = _time(scene, backend, precision, tol, cap, pos, vel, ball, frames)
                it = used.get(tol, float(cap))
                out.append({"n": n, "backend": backend, "precision": precision,
                            "cg_tolerance": tol, "cg_max_iterations": cap, "iterations": it,
                            "unroll": unroll, "us_per_substep": us})
                turn = f" unroll {unroll:<2}" if unroll is not None else ""
                print(f"n={n:<4} {precision}{turn} tol {tol:<7g} cap {cap:<4} iterations "
                      f"{it:6.1f}  {us:8.1f} us/substep", flush=True)
    return out


@contextlib.contextmanager
def _unroll(unroll: int | None) -> Iterator[None]:
    """CLOTHBALL_CG_UNROLL set while a cloth is made (the engine reads it then)."""
    old = os.environ.get(UNROLL_ENV)
    if unroll is not None:
        os.environ[UNROLL_ENV] = str(unroll)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(UNROLL_ENV, None)
        else:
            os.environ[UNROLL_ENV] = old


def _time(scene: Scene, backend: str, precision: str, tol: float, cap: int, pos: Any,
          vel: Any, ball: Any, frames: int) -> float:
    """Median wall time (us) of a frame of one substep, from the given state."""
    c = _cloth(scene, backend, precision, tol, cap)
    c.set_state(pos, vel)
    c.set_ball(*ball)
    c.step(3)  # warm-up: the frame's graph is captured on first use
    c.set_state(pos, vel)
    c.set_ball(*ball)
    times = []
    for _ in range(frames):
        t0 = time.perf_counter()
        c.step(1)
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e6


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m clothball.game.study.cg_cost",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--backend", default="cuda", choices=("cpu", "cuda"))
    p.add_argument("--sizes", default="40,80", help="comma-separated n")
    p.add_argument("--precisions", default="float32,float64")
    p.add_argument("--frames", type=int, default=100, help="timed frames per case")
    p.add_argument("--unroll", help="comma-separated CG iterations per turn of the CUDA "
                   "loop (1-32) to compare; default: the engine's")
    p.add_argument("--json", metavar="FILE")
    a = p.parse_args(argv)
    try:
        sizes = [int(s) for s in a.sizes.split(",")]
    except ValueError:
        print(f"cg_cost: --sizes: expected whole numbers, got {a.sizes!r}", file=sys.stderr)
        return 2
    unrolls: list[int | None] | None = None
    if a.unroll:
        try:
            unrolls = [int(u) for u in a.unroll.split(",")]
        except ValueError:
            unrolls = []
        if not unrolls or not all(1 <= u <= 32 for u in unrolls):
            print(f"cg_cost: --unroll: expected whole numbers from 1 to 32, got {a.unroll!r}",
                  file=sys.stderr)
            return 2
    rows = [r for n in sizes
            for r in measure(n, a.backend, a.precisions.split(","), a.frames, unrolls)]
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
