"""The short-horizon error through the impact (tests/study/test_accuracy.py's short drop)
at four halvings of the step from the integrator's bound, for several drop heights: the
local slopes, and those of the geometric mean over the heights. Run from the repository
root: ``python tools/lab/impact_slopes.py velocity_verlet 0.92,0.93,0.94,0.95``."""

from __future__ import annotations

import math
import sys

import numpy as np
from clothball.game.study.accuracy import (
    contact_time,
    fig4_start,
    impact_speed,
    make_sim,
    run_trajectory,
    short_error,
    short_window_end,
    start_substeps,
)

sys.path.insert(0, "tests/study")
from test_accuracy import short_drop  # noqa: E402


def slopes(errors: list[float]) -> list[str]:
    return [f"{math.log2(a / b):.2f}" for a, b in zip(errors, errors[1:], strict=False)]


def main() -> None:
    integrator, heights = sys.argv[1], [float(a) for a in sys.argv[2].split(",")]
    every = []
    for y in heights:
        scene = short_drop().with_changes({"ball": {"position": [0.0, y, 0.0]}})
        start = fig4_start(scene)
        s0 = start_substeps(scene, integrator, impact_speed(scene, start))
        levels = [s0 * 2**k for k in range(4)]
        ref_sim, _ = make_sim(scene, integrator, "float64", levels[-1] * 16, "cpu",
                              reference=True)
        ref = run_trajectory(ref_sim, scene, start, 0.08, 2)
        contact = contact_time(ref, scene["ball"]["radius"])
        end = short_window_end(contact, 0.02, 0.08, 0.6)
        errors = []
        for s in levels:
            sim, _ = make_sim(scene, integrator, "float64", s, "cpu")
            errors.append(short_error(run_trajectory(sim, scene, start, 0.08, 2), ref, end))
        every.append(errors)
        print(f"ball at {y} m: contact {contact * 1e3:.0f} ms, substeps {levels}, "
              f"local slopes {slopes(errors)}", flush=True)
    mean = np.exp(np.mean(np.log(every), axis=0))
    print(f"{integrator}: local slopes of the geometric mean {slopes(list(mean))}")


if __name__ == "__main__":
    main()
