"""Lab (issue 42): the default's static sag with lumped masses by area (interior L^2, edges
L^2 / 2, corners L^2 / 4 of the sheet's density) against the engine's uniform mass / n^2:
Newton's method on the oracle's forces, gravity a load of each node's own mass.

    python tools/lab/sag_mass_by_area.py 13,25,49      # n = 49: a few minutes a solve
"""

import sys
import time

import numpy as np
from clothball.game import Scene
from clothball.game.sim.oracle import ReferenceCloth
from clothball.game.study import integrators_ref as ir
from clothball.game.study.grid import sized


def solve(scene, by_area, tol=1e-7):
    s0 = ir.with_effects(scene, ["ball", "damping", "gravity"])
    ref = ReferenceCloth(s0)
    n = s0.n
    w = np.ones((n, n))
    if by_area:
        for edge in (np.s_[0, :], np.s_[-1, :], np.s_[:, 0], np.s_[:, -1]):
            w[edge] *= 0.5
    m = scene["cloth"]["mass"] * w / w.sum()
    load = m[..., None] * np.array(scene["sim"]["gravity"])
    zero_b = np.zeros(3)
    x = ref.pos.copy()
    weight = scene.node_mass * 9.81
    kscale = s0["cloth"]["k_structural"]

    def res(p):
        return ref.forces(p, np.zeros_like(p))[0] + load

    def en(p):
        return ir.potential_energy(s0, p, zero_b, ref.hips) - float(np.sum(load * p))

    x, _, it = ir.damped_newton(s0, x, res, en, tol * weight, kscale, 400)
    return ir.centre_sag(scene, x), it

base = Scene.load("default")
for n in (int(x) for x in (sys.argv[1] if len(sys.argv) > 1 else "13,25,49").split(",")):
    for by_area in (False, True):
        t = time.time()
        sag, it = solve(sized(base, n), by_area)
        print(n, "by area" if by_area else "uniform", f"{sag*1e3:.3f} mm", it, "iterations",
              f"{time.time()-t:.0f} s", flush=True)
