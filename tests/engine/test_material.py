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
from clothball.game.sim.oracle import (
    ReferenceCloth,
    grip_points,
    grips,
    node_contact_stiffness,
    node_damping,
)

from tests.engine.test_engine_vs_oracle import _drive, allowed_drift


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
    # The units: beta1 = gamma m_node (an interior node's mass, total / (n - 1)^2: masses by
    # area), k_b = kappa L^2 (an edge: half).
    assert node_damping(s) == pytest.approx(7.5 * 0.3 / (n - 1) ** 2, rel=1e-14)
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
        # One substep of 0.1 ms (inside the stability bound) measures the force.
        "sim": {"effects": ["ball"], "substeps": 1, "precision": "float64", "frame_dt": 1e-4},
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


# --- the hands' grip (coupling.grip_radius) ------------------------------------------------
def grip_scene(n: int, grip: float, **sim: object) -> Scene:
    return Scene.from_dict({
        "cloth": {"n": n, "k_shear": 300.0, "damping_rate": 5.0},
        "coupling": {"grip_radius": grip},
        "sim": {"effects": ["structural", "shear", "gravity", "damping", "coupling"],
                "precision": "float64", "substeps": 8, **sim},
    })


@pytest.mark.parametrize(("n", "grip"), [(4, 0.3), (9, 0.3), (16, 0.05), (16, 0.2),
                                          (25, 0.0417), (33, 0.0)])
def test_a_grip_moves_as_the_oracle(backend: str, n: int, grip: float) -> None:
    """The hands pulled off their rest points: the engine (grip derived in native/core)
    against the oracle (its own derivation: each node's share the grip's density integrated
    against its hat function, exactly), positions, the points the hands hold and their
    forces; n = 4 caps the grip at the corner node, at n = 16 a = 0.05 is within a spacing
    (the corner node alone), at 25 the grip ends just past the first node (the second's hat
    meets it over 0.1 % of a spacing)."""
    s = grip_scene(n, grip)
    cloth, ref = Cloth(s, backend=backend), ReferenceCloth(s)
    hips = cloth.hips() + np.array([[0.03, 0.02, -0.01], [-0.02, 0.04, 0.0],
                                    [0.0, -0.03, 0.02], [0.01, 0.0, 0.05]])
    cloth.set_hips(hips)
    ref.hips = hips.copy()
    cloth.step(40)
    ref.step(40, 8)
    np.testing.assert_allclose(cloth.positions(), ref.pos, rtol=0, atol=1e-12)
    np.testing.assert_allclose(cloth.corners()[0], grip_points(s, ref.pos), rtol=0, atol=1e-12)
    # The held points' velocities: 1e-10, or what rounding allows where the hands whip a
    # light corner (n = 33, one node a hand: 46 m/s, and two oracles one rounding apart
    # end 2e-10 m/s apart), derived as test_engine_vs_oracle derives its tolerances.
    drift = allowed_drift(s, "float64", 8, hips, drive=lambda sim: _drive(sim, s, 40, 8, hips))
    np.testing.assert_allclose(cloth.corners()[1], grip_points(s, ref.pos, ref.vel), rtol=0,
                               atol=max(1e-10, drift))
    np.testing.assert_allclose(cloth.corner_forces(), ref.corner_forces(), rtol=0, atol=1e-9)


@pytest.mark.parametrize("n", [5, 16, 48, 97])
def test_a_grip_holds_with_its_stiffness_whatever_n(n: int) -> None:
    """Every hand moved by the same d from the cloth at rest, coupling alone: one substep
    gives the cloth the momentum 4 K d dt at every n (the grip's nodes share K), and each
    hand reads the force -K d."""
    K, d = 1000.0, np.array([0.004, -0.002, 0.001])
    s = Scene.from_dict({"cloth": {"n": n}, "coupling": {"grip_radius": 0.06},
                         "sim": {"effects": ["coupling"], "precision": "float64",
                                 "frame_dt": 1e-5, "substeps": 1}})
    cloth = Cloth(s, backend="cpu")
    cloth.set_hips(cloth.hips() + d)
    np.testing.assert_allclose(cloth.corner_forces(), np.broadcast_to(-K * d, (4, 3)), rtol=1e-12)
    cloth.step(1)
    dt = s["sim"]["frame_dt"]
    momentum = (s.node_masses * cloth.velocities()).sum(axis=(0, 1))
    np.testing.assert_allclose(momentum, 4 * K * d * dt, rtol=1e-12)
    held = {(g.i, g.j) for g in grips(s)}
    moved = {(int(i), int(j)) for i, j in zip(*np.nonzero(np.abs(cloth.velocities()).sum(-1)),
                                               strict=True)}
    u = 0.06 / s.rest_length  # nodes m whose hat meets the grip: (m - 1) L < a, if a > L
    per_edge = min(math.ceil(u), (n - 2) // 2) if u > 1 else 0
    assert moved == held and len(held) == 4 * (1 + 2 * per_edge)


def test_a_grip_shares_its_stiffness_as_its_density() -> None:
    """The shares (oracle) are the grip's density rho(x) = (1 - (x / 3)^2)^2 (a = 3 L, x in
    spacings) integrated against each node's hat function, the corner's half hat on both
    edges, derived by hand: where a hat lies within the density, node m's integral is
    1 - 2 (m^2 + 1/6) / 9 + (m^4 + m^2 + 1/15) / 81 (the hat's moments 1, 1/6, 1/15): node 1
    931/1215, node 2 391/1215; node 3's hat meets the density on [2, 3] only, the integral
    of (x - 2) rho, 73/2430; the corner 2 x 1171/2430. The total is the density's, 16/5 =
    3888/1215 (the hats sum to one), so the shares are 1171, 931, 391 and 36.5 over 3888."""
    s = grip_scene(11, 0.3)  # L = 0.1
    shares = {(g.i, g.j): g.share for g in grips(s) if g.corner == 0}
    assert shares == pytest.approx({(0, 0): 1171 / 3888, (0, 1): 931 / 3888,
                                    (1, 0): 931 / 3888, (0, 2): 391 / 3888, (2, 0): 391 / 3888,
                                    (0, 3): 73 / 7776, (3, 0): 73 / 7776}, rel=1e-12)
