"""Hard cases stay numerically stable: every case on both backends, each with real
assertions (finite values, energy bounded by the work put in, strain within the limit,
the ball above the cloth it rests on)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from clothball.game import Cloth, Scene, SceneError, SimulationError
from clothball.game.sim.cloth import UnstableSceneWarning, rest_positions
from clothball.game.sim.config import node_values
from clothball.game.sim.stability import (
    SAFETY,
    SWITCH_MARGIN,
    auto_substeps,
    euler_dt_bound,
    node_stiffness,
    stable_dt,
)
from clothball.game.study.energy import cloth_energy


def scene(n: int = 16, **sections: dict) -> Scene:
    d: dict = {"cloth": {"n": n}}
    for name, table in sections.items():
        d.setdefault(name, {}).update(table)
    return Scene.from_dict(d)


def cloth_height_under(cloth: Cloth, x: float, z: float) -> float:
    """Height of the cloth node nearest to (x, z) horizontally."""
    pos = cloth.positions()
    d2 = (pos[..., 0] - x) ** 2 + (pos[..., 2] - z) ** 2
    i, j = np.unravel_index(np.argmin(d2), d2.shape)
    return float(pos[i, j, 1])


def strains(pos: np.ndarray, L: float) -> np.ndarray:
    sx = np.linalg.norm(pos[:, 1:] - pos[:, :-1], axis=-1) / L - 1
    sz = np.linalg.norm(pos[1:, :] - pos[:-1, :], axis=-1) / L - 1
    return np.concatenate([sx.ravel(), sz.ravel()])


def energy_scale(s: Scene) -> float:
    """m g h of the cloth: the natural unit of its energy."""
    return s["cloth"]["mass"] * 9.81 * s["cloth"]["size"]


# --- the stability bound ---------------------------------------------------------------


def test_bound_inside_stays_bounded_and_well_outside_blows_up(backend: str) -> None:
    base = scene(
        12,
        cloth={"k_structural": 5e4, "structural_two_sided": True},
        sim={"effects": ["structural", "gravity", "coupling"]},
    )
    bound = stable_dt(base) / SAFETY  # the bound itself, without the safety margin
    frame = base["sim"]["frame_dt"]

    inside = base.with_changes({"sim": {"substeps": int(np.ceil(frame / (0.95 * bound)))}})
    c = Cloth(inside, backend=backend, precision="float64")
    e0 = cloth_energy(c)
    c.set_hips(c.hips() + [0.0, 0.05, 0.0])  # put some work in
    c.step(300)
    assert np.all(np.isfinite(c.positions()))
    assert cloth_energy(c) < e0 + 10 * energy_scale(inside)

    # Four times the bound: beyond the true limit (Gershgorin overestimates it at most 2x
    # for this grid), so the oscillation must grow until the state is no longer finite.
    outside = base.with_changes(
        {"sim": {"substeps": max(1, int(frame / (4 * bound))), "allow_unstable": True}}
    )
    assert frame / outside["sim"]["substeps"] > 3.5 * bound
    with pytest.warns(UnstableSceneWarning, match="stability bound"):
        c = Cloth(outside, backend=backend, precision="float64")
    c.set_hips(c.hips() + [0.0, 0.05, 0.0])
    with pytest.raises(SimulationError, match="non-finite"):
        c.step(3000)


def test_fixed_dt_beyond_the_bound_is_refused() -> None:
    s = scene(20, cloth={"k_structural": 1e5}, sim={"substeps": 1})
    with pytest.raises(SceneError, match=r"stability bound .* at least \d+ substeps"):
        Cloth(s, backend="cpu")


def test_auto_substeps_follow_stiffness_and_ball_speed() -> None:
    soft, stiff = scene(20), scene(20, cloth={"k_structural": 1e5})
    assert auto_substeps(stiff) > auto_substeps(soft)
    c = Cloth(soft, backend="cpu")
    before = c.substeps
    c.set_ball([0.0, 2.0, 0.0], [0.0, -400.0, 0.0])  # a setter the bound depends on
    assert c.substeps > before
    assert c.dt * 400.0 <= 0.2 * soft["ball"]["radius"]  # no more than 1/5 radius a substep


def test_a_lightly_damped_tension_only_net_shaken_hard_keeps_its_energy() -> None:
    """Tension-only springs switch off as they cross their rest length; across that kink
    semi-implicit Euler conserves no energy. A stiff net of them, damped at the scene
    default's 2 /s (damping ratio 3.6e-5 at its fastest mode), every node kicked at 3 m/s:
    at 0.9 of the linear bound (17 substeps) the energy grows past the kick's within 10 s,
    at the automatic substeps (SWITCH_MARGIN of the bound: 18) it only falls."""
    s = scene(24, cloth={"k_structural": 1e5},
              sim={"effects": ["structural", "gravity", "damping", "coupling"]})
    m = s.node_mass
    linear = euler_dt_bound(node_stiffness(s) / m, node_values(s).damping / m)
    frame = s["sim"]["frame_dt"]
    assert math.ceil(frame / (SAFETY * linear)) == 17  # what the bound took before
    auto = Cloth(s, backend="cpu", precision="float64")
    assert auto.substeps == math.ceil(frame / (SWITCH_MARGIN * linear)) == 18
    gains = {}
    for substeps in (17, auto.substeps):
        fixed = s.with_changes({"sim": {"substeps": substeps, "allow_unstable": True}})
        if substeps < auto.substeps:  # beyond the bound now: accepted with a warning
            with pytest.warns(UnstableSceneWarning):
                c = Cloth(fixed, backend="cpu", precision="float64")
        else:
            c = Cloth(fixed, backend="cpu", precision="float64")
        kick = np.random.default_rng(1).normal(size=c.velocities().shape) * 3.0
        c.set_state(c.positions(), kick)
        e0 = cloth_energy(c)
        c.step(1200)
        assert np.all(np.isfinite(c.positions()))
        gains[substeps] = cloth_energy(c) - e0
    assert gains[17] > 0.0, gains
    assert gains[auto.substeps] < 0.0, gains


# --- the hard cases ----------------------------------------------------------------------


def test_stiff_springs_1e5(backend: str) -> None:
    s = scene(20, cloth={"k_structural": 1e5})
    c = Cloth(s, backend=backend)
    e0 = cloth_energy(c)
    c.step(400)
    assert np.all(np.isfinite(c.positions())) and np.all(np.isfinite(c.velocities()))
    # Static hands put no work in: energy may only fall (damping, contact) up to the
    # integrator's small oscillation.
    assert cloth_energy(c) <= e0 + 0.01 * energy_scale(s)


def test_heavy_ball_dropped_from_2m(backend: str) -> None:
    """A ball of 10x the cloth's mass (5 kg, 111 J at impact) dropped from 2 m is caught.

    It needs edge contact (ball.contact = "edges"): with the paper's node contact (eq. 4)
    the sphere passes between the nodes through the spring segments, even with springs
    at 1e5 N/m (strain only 0.12, the ball ends 5 m below the cloth). And it needs a stiff
    cloth: at the default k_structural = 2000 N/m the springs stretch to strain 0.8 and
    the ball tears through with edge contact too (too weak a cloth for 111 J: physics, not
    a bug). With both, the float64 oracle (ReferenceCloth) at the automatic 18 substeps
    keeps the ball at least 0.065 m above the cloth at strain 0.04, and it bounces back up."""
    s = scene(
        24,
        cloth={"k_structural": 1e5},  # as test_stiff_springs_1e5
        ball={"mass": 5.0, "position": [0.0, 3.0, 0.0], "contact": "edges"},
    )
    c = Cloth(s, backend=backend)
    e0 = cloth_energy(c)
    lowest_gap = np.inf
    worst = 0.0
    for _ in range(150):  # 1.5 s: the fall, the impact and the bounces
        c.step(10)
        (bx, by, bz), _ = c.ball()
        lowest_gap = min(lowest_gap, by - cloth_height_under(c, bx, bz))
        worst = max(worst, float(strains(c.positions(), s.rest_length).max()))
        assert np.all(np.isfinite(c.positions())) and np.all(np.isfinite(c.velocities()))
    assert lowest_gap > 0.0, "the ball went through the cloth"
    # Static hands put no work in: the total energy (cloth, ball, contact) may only fall.
    assert cloth_energy(c) <= e0 + 0.01 * energy_scale(s)
    assert worst < 0.2


def test_ball_thrown_down_at_20_m_s(backend: str) -> None:
    s = scene(24, ball={"position": [0.0, 1.5, 0.0], "velocity": [0.0, -20.0, 0.0]})
    c = Cloth(s, backend=backend)
    assert c.dt * 20.0 <= 0.2 * s["ball"]["radius"]  # the tunnelling bound holds
    lowest_gap = np.inf
    for _ in range(300):
        c.step(1)
        (bx, by, bz), _ = c.ball()
        lowest_gap = min(lowest_gap, by - cloth_height_under(c, bx, bz))
    assert np.all(np.isfinite(c.positions()))
    assert lowest_gap > 0.0, "the ball tunnelled through the cloth"


def _yank(backend: str, limit: bool) -> float:
    effects = ["structural", "gravity", "damping", "coupling"] + (["strain_limit"] if limit else [])
    s = scene(16, sim={"effects": effects})
    c = Cloth(s, backend=backend)
    h = c.hips()
    h[0] += [-5.0, 0.0, 0.0]
    c.set_hips(h)
    worst = 0.0
    for _ in range(50):
        c.step(4)
        pos = c.positions()
        assert np.all(np.isfinite(pos)) and np.all(np.isfinite(c.velocities()))
        worst = max(worst, float(strains(pos, s.rest_length).max()))
    return worst


def test_corner_yanked_5m_and_held(backend: str) -> None:
    """Finite throughout, with and without strain limiting; limiting lowers the strain."""
    free, limited = _yank(backend, False), _yank(backend, True)
    assert limited < 0.75 * free


def test_yanked_corner_strain_within_the_limit(backend: str) -> None:
    """The scene's default 10 passes hold the limit (measured worst: 0.1000085 in float64;
    the 1e-3 relative margin covers the passes' residual and float32's rounding of max_len)."""
    assert _yank(backend, True) <= Scene.from_dict({"cloth": {"n": 2}})["strain_limit"][
        "max_strain"
    ] * (1 + 1e-3)


def test_all_corners_released_fall_freely(backend: str, precision: str) -> None:
    """No coupling: the cloth at rest length falls as one body, no spurious spring forces."""
    s = scene(16, sim={"effects": ["structural", "shear", "bend", "gravity"]})
    c = Cloth(s, backend=backend, precision=precision)
    c.step(100)
    k, dt = 100 * c.substeps, c.dt
    want = rest_positions(s)
    want[..., 1] -= 9.81 * dt * dt * k * (k + 1) / 2
    tol = 1e-5 if precision == "float32" else 1e-11
    np.testing.assert_allclose(c.positions(), want, rtol=0, atol=tol)


def test_all_nodes_coincident(backend: str) -> None:
    s = scene(
        10,
        cloth={"structural_two_sided": True},
        sim={"effects": ["structural", "shear", "bend", "gravity", "damping"]},
    )
    c = Cloth(s, backend=backend, precision="float64")
    pos = np.zeros((10, 10, 3))
    pos[..., 1] = 1.0
    c.set_state(pos, np.zeros_like(pos))
    c.step(10)
    p = c.positions()
    assert np.all(np.isfinite(p)) and np.all(np.isfinite(c.velocities()))
    # Coincident nodes have no spring direction: they only fall, together.
    assert np.ptp(p, axis=(0, 1)).max() < 1e-12


@pytest.mark.parametrize("where", ["node", "edge"])
def test_ball_resting_exactly_on_a_node_or_an_edge(backend: str, where: str) -> None:
    """The ball set down touching the cloth exactly above a node, or exactly above the middle
    of a spring (contact shared by two nodes), settles and stays on top."""
    s = scene(17)
    c = Cloth(s, backend=backend, precision="float64")
    rest = rest_positions(s)
    under = rest[8, 8] if where == "node" else 0.5 * (rest[8, 8] + rest[8, 9])
    c.set_ball(under + [0.0, s["ball"]["radius"], 0.0], [0.0, 0.0, 0.0])
    gaps = []
    for _ in range(100):
        c.step(5)
        (bx, by, bz), _ = c.ball()
        gaps.append(by - cloth_height_under(c, bx, bz))
    assert np.all(np.isfinite(c.positions()))
    assert min(gaps) > 0.0, "the ball sank through the cloth"


def test_ball_centre_exactly_on_a_node(backend: str) -> None:
    """Distance 0 between the ball's centre and a node: no division by zero; the node is
    pushed down, the ball up, onto the cloth."""
    s = scene(17)
    c = Cloth(s, backend=backend, precision="float64")
    c.set_ball(rest_positions(s)[8, 8], [0.0, 0.0, 0.0])
    for _ in range(100):
        c.step(5)
    (bx, by, bz), _ = c.ball()
    assert np.all(np.isfinite(c.positions())) and np.isfinite(by)
    assert by > cloth_height_under(c, bx, bz)


def test_zero_damping_long_run_energy_drift(backend: str) -> None:
    """10^5 frames without damping: semi-implicit Euler is symplectic, so the energy
    oscillates about a fixed level but does not drift: the mean of the last window stays
    within the band the energy oscillates in during the first window."""
    s = scene(
        8,
        cloth={"structural_two_sided": True},
        sim={"effects": ["structural", "gravity", "coupling"]},
    )
    c = Cloth(s, backend=backend, precision="float64")
    c.set_hips(c.hips() + [0.0, 0.02, 0.0])
    c.step(1)
    windows = []
    for _ in range(10):
        es = []
        for _ in range(100):
            c.step(100)
            es.append(cloth_energy(c))
        windows.append(es)
    assert c.frame == 1 + 10 * 100 * 100
    band = np.ptp(windows[0])
    drift = abs(np.mean(windows[-1]) - np.mean(windows[0]))
    assert drift <= band, f"energy drifted by {drift:.3g} J (oscillation band {band:.3g} J)"


def test_largest_cpu_cloth() -> None:
    """n = 4096 (16.8 M nodes), the largest size the CPU backend is built for."""
    s = scene(
        4096, cloth={"mass": 1e4, "k_structural": 10.0}, sim={"effects": ["structural", "gravity"]}
    )
    c = Cloth(s, backend="cpu", precision="float32")
    assert c.substeps == 1
    c.step(2)
    y = c.positions()[..., 1]
    k, dt = 2, c.dt
    assert np.all(np.isfinite(y))
    np.testing.assert_allclose(y, 1.0 - 9.81 * dt * dt * k * (k + 1) / 2, atol=1e-6)


def test_larger_than_cpu_limit_is_refused() -> None:
    with pytest.raises(ValueError, match="n = 4097"):
        Cloth(scene(4097), backend="cpu")


def test_float32_vs_float64_long_run(backend: str) -> None:
    s = scene(16, sim={"effects": ["structural", "gravity", "damping", "coupling"]})
    a = Cloth(s, backend=backend, precision="float32")
    b = Cloth(s, backend=backend, precision="float64")
    h = a.hips() + np.array([[0.0, 0.02, 0.0]] * 4)
    a.set_hips(h)
    b.set_hips(h)
    gaps = []
    for _ in range(20):
        a.step(250)
        b.step(250)
        gaps.append(np.abs(a.positions() - b.positions()).max())
    # 5 s of simulated time: the gap is bounded (it does not grow over the run). Its size,
    # centimetres here, is what float32 costs: see docs/accuracy.md.
    assert np.all(np.isfinite(gaps))
    assert max(gaps[10:]) <= 2 * max(gaps[:10])


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_hands_are_refused(backend: str, bad: float) -> None:
    c = Cloth(scene(8), backend=backend)
    h = c.hips()
    h[2, 1] = bad
    with pytest.raises(ValueError, match="finite"):
        c.set_hips(h)
    np.testing.assert_array_equal(c.hips()[2], rest_positions(c.scene)[-1, -1])
    c.step(5)
    assert np.all(np.isfinite(c.positions()))


def test_nan_state_detected_after_the_frame(backend: str) -> None:
    """A NaN anywhere in the cloth (not only at a corner) is caught after the frame."""
    s = scene(32, sim={"effects": ["structural", "gravity"]})
    c = Cloth(s, backend=backend, precision="float64")
    pos = rest_positions(s)
    pos[15, 16, 0] = 1e308  # finite, but its spring lengths overflow: NaN forces
    c.set_state(pos, np.zeros_like(pos))
    with pytest.raises(SimulationError):
        c.step(1)
