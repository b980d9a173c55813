"""The float64 reference integrators: the force Jacobian against finite differences, each
integrator's order of accuracy, the implicit one's stability, and the Newton equilibrium.

Orders are measured the way ``clothball accuracy`` measures them: error against a run of
the same integrator with a 16x smaller step than the finest one, slope of log error
against log dt fitted over three halvings.
"""

from __future__ import annotations

import numpy as np
import pytest
from clothball.game import Scene
from clothball.game.sim.stability import stable_dt
from clothball.game.study.accuracy import fitted_order
from clothball.game.study.integrators_ref import (
    ORDERS,
    IntegratingCloth,
    Linearization,
    centre_sag,
    force_jvp,
    static_equilibrium,
    stiffness_diag,
)

ALL = ["structural", "shear", "bend", "gravity", "damping", "ball", "coupling"]


def contact_scene() -> Scene:
    """Every effect, two-sided (compressible) springs, and the ball sunk into the cloth."""
    return Scene.from_dict({
        "cloth": {"n": 7, "size": 0.5, "structural_two_sided": True},
        "ball": {"position": [0.01, 1.0, 0.02], "radius": 0.12},
        "sim": {"effects": ALL},
    })


def jittered(scene: Scene, seed: int = 1) -> tuple[IntegratingCloth, np.ndarray]:
    ic = IntegratingCloth(scene)
    rng = np.random.default_rng(seed)
    return ic, ic.pos + 0.01 * rng.standard_normal(ic.pos.shape)


def test_jvp_matches_finite_differences() -> None:
    scene = contact_scene()
    ic, pos = jittered(scene)
    bp = ic.ball_pos
    assert len(Linearization(scene, pos, bp).contact[0]) >= 3  # several nodes in contact
    rng = np.random.default_rng(2)
    w, wb = rng.standard_normal(pos.shape), rng.standard_normal(3)
    jn, jb = force_jvp(scene, pos, bp, w, wb)
    h = 1e-6
    zero = np.zeros_like(pos)
    fp, fbp = ic.all_forces(pos + h * w, zero, bp + h * wb, np.zeros(3))
    fm, fbm = ic.all_forces(pos - h * w, zero, bp - h * wb, np.zeros(3))
    # Central differences: error ~ h^2 |f'''| plus rounding |f| eps / h.
    scale = np.abs(jn).max()
    np.testing.assert_allclose((fp - fm) / (2 * h), jn, rtol=0, atol=1e-7 * scale)
    np.testing.assert_allclose((fbp - fbm) / (2 * h), jb, rtol=0, atol=1e-7 * scale)


def test_definite_jacobian_is_negative_semidefinite() -> None:
    scene = contact_scene()
    ic, pos = jittered(scene)
    rng = np.random.default_rng(3)
    exact_min = np.inf
    for _ in range(20):
        w, wb = rng.standard_normal(pos.shape), rng.standard_normal(3)
        jn, jb = force_jvp(scene, pos, ic.ball_pos, w, wb, definite=True)
        assert np.sum(w * jn) + wb @ jb <= 1e-9 * np.abs(jn).max()
        en, eb = force_jvp(scene, pos, ic.ball_pos, w, wb, definite=False)
        exact_min = min(exact_min, -(np.sum(w * en) + wb @ eb))
    # (The exact Jacobian is the one the definite projection changes: compressed pairs.)
    assert np.isfinite(exact_min)


def test_stiffness_diag_is_the_diagonal() -> None:
    scene = contact_scene()
    ic, pos = jittered(scene)
    dn, db = stiffness_diag(scene, pos, ic.ball_pos, definite=False)
    for idx in [(0, 0, 0), (3, 3, 1), (2, 4, 2), (6, 1, 1)]:
        e = np.zeros_like(pos)
        e[idx] = 1.0
        assert -force_jvp(scene, pos, ic.ball_pos, e, np.zeros(3))[0][idx] == pytest.approx(dn[idx])
    for c in range(3):
        eb = np.zeros(3)
        eb[c] = 1.0
        got = -force_jvp(scene, pos, ic.ball_pos, np.zeros_like(pos), eb)[1][c]
        assert got == pytest.approx(db[c])


def smooth_scene() -> Scene:
    """A smooth problem (two-sided springs, no contact): the hands pulled 2 cm, so every
    node moves; light damping."""
    return Scene.from_dict({
        "cloth": {"n": 5, "size": 0.4, "structural_two_sided": True, "damping": 0.01},
        "sim": {"effects": ["structural", "gravity", "damping", "coupling"]},
    })


def run(scene: Scene, integrator: str, substeps: int, frames: int) -> np.ndarray:
    ic = IntegratingCloth(scene, integrator, cg_tol=1e-12)
    ic.hips = ic.hips + np.array([[0.02, 0.01, 0.0]] * 4)
    ic.step(frames, substeps)
    return ic.pos.copy()


@pytest.mark.parametrize("integrator", list(ORDERS))
def test_error_order(integrator: str) -> None:
    scene = smooth_scene()
    frames = 6
    levels = [2, 4, 8]
    ref = run(scene, integrator, levels[-1] * 16, frames)
    dts, errs = [], []
    for s in levels:
        dts.append(scene["sim"]["frame_dt"] / s)
        errs.append(np.sqrt(np.mean(np.sum((run(scene, integrator, s, frames) - ref) ** 2, -1))))
    assert dts[0] < stable_dt(scene)  # the explicit ones are inside their bound throughout
    order = fitted_order(dts, errs)
    assert abs(order - ORDERS[integrator]) < 0.25, (integrator, order, errs)


def test_verlet_is_textbook_verlet_without_damping() -> None:
    """Undamped, the scheme is x' = x + dt v + dt^2/2 a, v' = v + dt/2 (a + a')."""
    scene = Scene.from_dict({"cloth": {"n": 4, "structural_two_sided": True},
                             "sim": {"effects": ["structural", "gravity", "coupling"]}})
    ic = IntegratingCloth(scene, "velocity_verlet")
    ic.hips = ic.hips + 0.01
    m, dt = scene.node_masses, 1e-4
    x, v = ic.pos.copy(), ic.vel.copy()
    a = ic.forces(x, v)[0] / m
    ic.substep(dt)
    x1 = x + dt * v + 0.5 * dt * dt * a
    a1 = ic.forces(x1, v)[0] / m
    np.testing.assert_allclose(ic.pos, x1, rtol=0, atol=1e-15)
    np.testing.assert_allclose(ic.vel, v + 0.5 * dt * (a + a1), rtol=0, atol=1e-12)


def test_implicit_bounded_where_semi_implicit_euler_blows_up() -> None:
    scene = Scene.from_dict({"cloth": {"n": 6, "size": 0.5},
                             "sim": {"effects": ["structural", "gravity", "damping",
                                                 "coupling"]}})
    # One substep a frame, of 10x the explicit bound (stable_dt includes a 0.9 safety
    # margin: 10 / 0.9 times the bound itself).
    scene = scene.with_changes({"sim": {"frame_dt": 10 * stable_dt(scene)}})
    substeps = 1
    explicit = IntegratingCloth(scene, "semi_implicit_euler")
    implicit = IntegratingCloth(scene, "implicit_euler")
    with np.errstate(all="ignore"):
        for _ in range(60):
            explicit.step(1, substeps)
    assert not np.all(np.abs(explicit.pos) < 100.0)  # exploded (or overflowed to inf/nan)
    e0 = implicit.energy()
    for _ in range(60):
        implicit.step(1, substeps)
        assert np.all(np.isfinite(implicit.pos))
        # Backward Euler only removes energy: never more than it started with.
        assert implicit.energy() <= e0 + 1e-9
    assert np.abs(implicit.pos - IntegratingCloth(scene).pos).max() < 0.5


def test_newton_equilibrium_is_a_fixed_point() -> None:
    scene = Scene.from_dict({"cloth": {"n": 7}})  # the classic effects; the ball is left out
    x, info = static_equilibrium(scene)
    assert info["max_residual_over_weight"] <= 1e-7
    assert 0.05 < centre_sag(scene, x) < 0.5
    for integ in ORDERS:
        quiet = Scene.from_dict({"cloth": {"n": 7},
                                 "sim": {"effects": ["structural", "gravity", "damping",
                                                     "coupling"]}})
        ic = IntegratingCloth(quiet, integ)
        ic.pos = x.copy()
        ic.step(5, 4)
        np.testing.assert_allclose(ic.pos, x, rtol=0, atol=1e-9)
