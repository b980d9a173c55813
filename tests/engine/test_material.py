"""Material values (independent of n) and the per-node values derived from them.

The engine derives per-node values in native/core (per_node); the oracle derives them on
its own in float64 (oracle.node_damping, node_contact_stiffness). These tests check the
two against each other, against today's default scene, and against the physics they
stand for: a damping rate per unit mass and a contact stiffness per area whose effect on
the cloth does not change with n.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from clothball.game import Cloth, Scene
from clothball.game.sim.config import node_values
from clothball.game.sim.oracle import node_contact_stiffness, node_damping


def material_scene(n: int, contact: str = "nodes", **cloth: float) -> Scene:
    return Scene.from_dict({
        "cloth": {"n": n, "size": 0.8, "mass": 0.3, "damping_rate": 7.5, **cloth},
        "ball": {"stiffness_per_area": 4e6, "contact": contact},
        "sim": {"effects": ["structural", "gravity", "damping", "ball", "coupling"]},
    })


@pytest.mark.parametrize("contact", ["nodes", "edges"])
@pytest.mark.parametrize("n", [2, 7, 16, 48, 131])
def test_engine_and_oracle_derive_the_same_per_node_values(n: int, contact: str) -> None:
    s = material_scene(n, contact)
    got = node_values(s)
    assert got.damping == pytest.approx(node_damping(s), rel=1e-14)
    assert got.ball_k == pytest.approx(node_contact_stiffness(s), rel=1e-14)
    # The units: beta1 = gamma m_node, k_b = kappa L^2 (an edge: half).
    assert node_damping(s) == pytest.approx(7.5 * 0.3 / n**2, rel=1e-14)
    share = 0.5 if contact == "edges" else 1.0
    assert node_contact_stiffness(s) == pytest.approx(4e6 * (0.8 / (n - 1)) ** 2 * share,
                                                      rel=1e-14)


def test_per_node_values_pass_through() -> None:
    """A scene with the paper's per-node keys runs with them, whatever n."""
    s = Scene.from_dict({"cloth": {"n": 23, "damping": 0.004}, "ball": {"stiffness": 321.0}})
    assert node_values(s).damping == node_damping(s) == 0.004
    assert node_values(s).ball_k == node_contact_stiffness(s) == 321.0


@pytest.mark.parametrize("n", [6, 12, 24])
def test_a_damping_rate_damps_every_grid_alike(n: int) -> None:
    """Nodes moving uniformly under damping alone: semi-implicit Euler multiplies
    every velocity by (1 - gamma dt) a substep, whatever n (per node, beta1 / m_node grows
    as n^2)."""
    gamma = 20.0
    s = Scene.from_dict({"cloth": {"n": n, "damping_rate": gamma},
                         "sim": {"effects": ["damping"], "substeps": 4,
                                 "precision": "float64"}})
    cloth = Cloth(s, backend="cpu")
    v0 = np.array([0.3, -0.2, 0.1])
    cloth.set_state(cloth.positions(), np.broadcast_to(v0, (n, n, 3)))
    cloth.step(25)
    dt = s["sim"]["frame_dt"] / 4
    want = v0 * (1.0 - gamma * dt) ** (25 * 4)
    # A few roundings a substep (beta1, 1 / m dt, the update), 100 substeps.
    rtol = 4 * 100 * np.finfo(np.float64).eps
    np.testing.assert_allclose(cloth.velocities(), np.broadcast_to(want, (n, n, 3)),
                               rtol=rtol, atol=0)


def _contact_force(n: int, contact: str, h: float, radius: float, kappa: float) -> float:
    """The ball's total contact force (upward), its centre h above a flat, still cloth:
    one substep's change of its velocity, gravity off."""
    s = Scene.from_dict({
        "cloth": {"n": n, "size": 0.4},
        "ball": {"stiffness_per_area": kappa, "radius": radius, "contact": contact,
                 "position": [0.0013, 1.0 + h, -0.0021], "damping": 0.0, "mass": 1.0},
        "sim": {"effects": ["ball"], "substeps": 1, "precision": "float64"},
    })
    cloth = Cloth(s, backend="cpu")
    cloth.step(1)
    return float(cloth.ball()[1][1] / s["sim"]["frame_dt"])


def test_contact_per_area_gives_the_continuum_force() -> None:
    """A ball of radius R whose centre is h above a flat sheet, with stiffness kappa per
    area, feels pi kappa h (R - h)^2 (the integral of kappa (R - r) h / r over the disc it
    cuts). With stiffness_per_area the grid's sum approaches it as the spacing halves: on
    the nodes fast (a sum over the disc), on the edges at first order (each row and column
    adds one contact at its segment nearest the centre, a line's worth: O(L) more)."""
    radius, h, kappa = 0.08, 0.05, 2e6
    want = math.pi * kappa * h * (radius - h) ** 2
    sizes = (33, 65, 129)
    err = {c: [_contact_force(n, c, h, radius, kappa) / want - 1 for n in sizes]
           for c in ("nodes", "edges")}
    assert abs(err["nodes"][-1]) < 1e-3 and abs(err["nodes"][0]) < 0.01, err
    edges = err["edges"]
    assert all(e > 0 for e in edges), err
    orders = [math.log2(a / b) for a, b in zip(edges, edges[1:], strict=False)]
    assert all(0.8 < p < 1.2 for p in orders), (edges, orders)
