"""Lab (issue 42): the GPU's larger range (n to 193) on the CPU, float64, one thread, with
one suspect changed at a time (``--set`` as in game/study/gamestart.py).

For each n: what ``tests/study/test_grid_convergence.py`` checks of the default and its
lightly damped variant (grid.measure's rest state and drop from it: sag, force on a hand
at rest, landing, lowest point, rebound; not the natural frequency), and what
``tests/study/test_game_start.py`` checks (the game's start, its trajectory's distances
between grids). Prints every value, the differences between neighbouring grids and, for
the trajectory, where the largest difference lies. n = 193 takes about a minute a run on
an unloaded 2-core VM.

    python tools/lab/larger_range.py --sizes 25,49,97,193
    python tools/lab/larger_range.py --set cloth.k_bend=0.0 --set cloth.structural_two_sided=true
"""

from __future__ import annotations

import argparse

import numpy as np
from clothball.game import Cloth, Scene
from clothball.game.study.gamestart import scene_changes, trajectory
from clothball.game.study.grid import GridRun, _drop, rest_state, sized

LIGHT_DAMPING = 10.0  # 1/s, as tests/study/test_grid_convergence.py's "light"
DROP = ("landing_s", "lowest_y_m", "lowest_s", "rebound_m")


def row(label: str, values: list[float], scale: float = 1e3) -> str:
    return (f"  {label:22}" + " ".join(f"{v * scale:10.3f}" for v in values) + "   diffs "
            + " ".join(f"{(b - a) * scale:+.3f}" for a, b in zip(values, values[1:],
                                                                 strict=False)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="25,49,97,193")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--substeps-x", type=int, default=0,
                    help="step the drops with this multiple of the automatic substeps")
    args = ap.parse_args()
    changes = scene_changes(args.set)
    default = Scene.load("default")
    default = default.with_changes(changes) if changes else default
    light = default.with_changes({"cloth": {"damping_rate": LIGHT_DAMPING}})
    ns = [int(x) for x in args.sizes.split(",")]
    rest: dict[str, list[float]] = {"sag_m": [], "corner_force_rest_n": []}
    drops: dict[str, dict[str, list[float]]] = {"default": {}, "light": {}}
    starts = []
    for n in ns:
        x, sag, force = rest_state(sized(default, n), "cpu", 1)  # light's is the same
        rest["sag_m"].append(sag)
        rest["corner_force_rest_n"].append(force)
        for name, scene in (("default", default), ("light", light)):
            s = sized(scene, n)
            sub = args.substeps_x * Cloth(s, backend="cpu").substeps
            run = GridRun(scene=name, n=n, substeps=sub)
            _drop(s, sub, "cpu", "float64", 1500, 1, x, run)
            for q in DROP:
                drops[name].setdefault(q, []).append(run.quantities[q])
        starts.append(trajectory(sized(default, n), sag=False))
    print(f"default {' '.join(args.set)}, n = {ns}")
    print(row("sag (mm)", rest["sag_m"]))
    print(row("hand force at rest (N)", rest["corner_force_rest_n"], 1.0))
    for name, qs in drops.items():
        for q, values in qs.items():
            print(row(f"{name} {q}", values))
    print("  game start:")
    for a, b in zip(starts, starts[1:], strict=False):
        diff = 1e3 * (a.samples() - b.samples())
        k = int(np.abs(diff).max(axis=1).argmax())
        print(f"    d({a.n},{b.n}) = {np.abs(diff).max():.2f} mm, largest at "
              f"{a.times_s[k]:.2f} s")
    for q in ("lowest_y_m", "lowest_s", "rebound_m"):
        print(row(f"start {q}", [r.quantities[q] for r in starts]))


if __name__ == "__main__":
    main()
