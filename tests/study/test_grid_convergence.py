"""The physics converges as the grid refines when the scene is in material units.

The game's default scene (material values) and a lightly damped variant of it (so that the
ball rebounds and the cloth rings) are measured on grids whose spacing halves (n - 1 = 24,
48, 96 on the CPU, ``slow``; to 192 on the GPU; the documentation tests below from 12),
each quantity against the same quantity on the other grids (no reference values are
hard-coded). Where
the physics converges, successive differences must shrink, or be below what the quantity
resolves (``RESOLVED``); the observed orders are printed
(``-s``) and recorded as test properties. The hands hold a grip of fixed length
(``coupling.grip_radius``); held by single nodes, point supports, the static sag and what
rides on it drift by a constant few mm per halving instead, the membrane's displacement
growing as log(1 / L) (``test_point_supports_drift_logarithmically``, the same scene with
grip_radius 0).

The default's cloth bends with a bending stiffness (``cloth.bending_stiffness``, a plate's
D) beside its bending springs; with the springs alone (``springs``: the default before, its
bending_stiffness 0) the rebound converges over n = 13-49 and turns at 97, the springs'
resistance to bending fading as the grid refines
(``test_a_bending_stiffness_makes_the_rebound_converge``).

The same scene in the paper's per-node units (``per_node_twin``: the per-node values the
default derives at n = 48, fixed on every grid) is measured too, as documentation of the
drift issue 30 reports (its table): there the ball's lowest point, rebound and landing do
not converge; the test asserts only that the drift is that large, not that it is absent.
That documentation, and the point supports', is of the ``springs`` cloth, the one the
issue measured: the bending stiffness moves the rebound and the lowest point over n =
13-49 too (from the springs' bending to the plate's, 8.9 mm of rebound from n = 25 to 49),
which would blur the units' and the supports' drifts with its own.

GPU (the larger range, ``gpu`` marker, CUDA float64):
    CLOTHBALL_REQUIRE_GPU=1 python3 -m pytest -q -s -m gpu tests/study/test_grid_convergence.py
"""

from __future__ import annotations

import functools
import math

import pytest
from clothball.game import Scene
from clothball.game.study.grid import (
    QUANTITIES,
    Convergence,
    GridRun,
    convergence,
    measure,
    per_node_twin,
    sized,
)

CPU_SIZES = (13, 25, 49)  # spacing 1/12, 1/24, 1/48
# Where the default's grip (10 cm, a smooth density: docs/scenes.md) is resolved: at n =
# 13 (L = 8.3 cm) it is the corner node and a tenth of the next, a point support, and its
# sag there is pre-asymptotic (97.6, 95.4, 95.4, 95.5 mm at n = 13-97: the first
# difference 2.1 mm, the others under 0.1). Issue 42's targets are from n = 25. On the
# GPU's range to n = 193 the default with its earlier bending stiffness (0.5 mN m) did not
# converge: its cloth under the resting ball snapped at times that move with n (the
# rebound -7.11, -0.30, +0.45 mm, the light variant's lowest point -5.04, -1.36, -1.92);
# with 2 mN m both converge (-6.90, -0.71, +0.07 and -2.10, -0.63, +0.04; CPU float64,
# which gave CUDA's figures at 0.5 mN m to the digit; docs/accuracy.md, "The larger
# range").
CONVERGING_SIZES = (25, 49, 97)
GPU_SIZES = (25, 49, 97, 193)
LIGHT_DAMPING = 10.0  # 1/s: what the default's per-node damping was at n = 16


def scenario(name: str) -> Scene:
    default = Scene.load("default")
    if name == "default":
        return default
    if name == "light":
        return default.with_changes({"cloth": {"damping_rate": LIGHT_DAMPING}})
    springs = default.with_changes({"cloth": {"bending_stiffness": 0.0}})
    if name == "springs":
        return springs
    if name == "per_node":
        return per_node_twin(springs)
    if name == "point":
        return springs.with_changes({"coupling": {"grip_radius": 0.0}})
    raise ValueError(name)


@functools.cache
def run(name: str, n: int, backend: str) -> GridRun:
    r = measure(sized(scenario(name), n), backend=backend, precision="float64")
    assert not r.failed, r.failed
    return r


# What converges in material units (successive differences shrink as the spacing halves).
# The default is overdamped (92 /s per unit mass): its ball rebounds a little and its corner
# force does not ring (its ring_hz is the analysis's floor, not a mode); the lightly damped
# variant rings. Not listed, because they do not converge here: the default's lowest point
# and its time, and the light variant's rebound and the time of its lowest point. That time
# is 355.6, 379.7, 379.8, 382.8, 385.4 ms at n = 13, 25, 49, 97, 193 (CPU float64):
# differences 24.1, 0.1, 3.0, 2.6 ms, all one way (the 0.1 a near-cancellation: at n = 49
# the ball sinks faster after the first push below, and the second pushes harder), order
# 0.2 from n = 49 on, where its height converges at order 1 (-10.8, -9.7, -5.8, -2.8 mm). Not
# an ill-conditioned minimum (the ball's acceleration there is 2-4 g, its vertex well
# fitted): the lightly damped cloth stops the ball in two pushes, and how much of its speed
# the first takes moves with n. At n = 13 (a spacing about the ball's radius) the first
# stops it and it hops on the few nodes; from n = 25 on it leaves the ball sinking at 0.46,
# 0.77, 0.89, 0.97 m/s (at 346 ms) and the second stops it. The default's, for comparison:
# 339.0, 340.1, 342.2, 348.1, 350.0 ms (differences 1.1, 2.1, 5.9, 1.9). With the bending
# springs alone (before the default had a bending stiffness) the default's rebound and the
# light's ringing turned at n = 97 on the GPU's range (docs/accuracy.md: the cloth under
# the ball).
CONVERGING = {
    "default": ("sag_m", "corner_force_rest_n", "landing_s", "rebound_m", "natural_hz"),
    "light": ("sag_m", "corner_force_rest_n", "landing_s", "lowest_y_m", "ring_hz",
              "natural_hz"),
}
# Below these a difference counts as converged whether or not the next one shrinks. The
# static sag: with the cloth assembled cell by cell (issue 42) it lies within 0.1 mm from
# n = 25 to 193 (95.432, 95.404, 95.482, 95.506 mm at n = 25, 49, 97, 193), two error
# terms of opposite sign meeting there, so its differences turn (-0.03, +0.08, +0.02 mm)
# where uniform masses moved it 1.8 mm at order 0.47; the landing rides on it (+0.02,
# +0.05, +0.02 ms). The light variant's ring: its estimate over the 1.2 s after the landing
# moves by up to 0.036 Hz as the window's ends move by a few frames (n = 49), and its
# differences from n = 49 are 0.003 and 0.014 Hz (docs/accuracy.md, "Cell-assembled
# springs").
RESOLVED = {"sag_m": 1e-4, "landing_s": 1e-4, "ring_hz": 0.03}


# What drifts at the rate point supports set (the "point" scene: each hand holds one node):
# a membrane held at a point stretches without bound near it (the strain falls as 1 / r,
# the displacement grows as log(1 / L)), so the whole cloth hangs lower by about the same
# length at every halving of the spacing, in either units (the static sag is the same in
# both). Issue 30's table saw this as the sag's slow growth; it is not the damping.
LOGARITHMIC = ("sag_m", "lowest_y_m")


def line_of(name: str, c) -> str:
    unit = QUANTITIES[c.name][0]
    return (f"{name:8} {c.name:20} " + "  ".join(f"n={n}: {v:.6g}" for n, v in zip(
        c.ns, c.values, strict=True)) + f" {unit}; differences "
        + ", ".join(f"{d:.3g}" for d in c.differences)
        + "; observed order " + ", ".join(f"{p:.2f}" for p in c.orders))


def check_converges(name: str, sizes: tuple[int, ...], backend: str, record) -> None:
    runs = [run(name, n, backend) for n in sizes]
    for q in CONVERGING[name]:
        c = convergence(runs, q)
        assert all(math.isfinite(v) for v in c.values), (q, c.values)
        line = line_of(name, c)
        print(line)
        record(f"{name}.{q}", line)
        d = [abs(v) for v in c.differences]
        assert all(b < a or b <= RESOLVED.get(q, 0.0) for a, b in zip(d, d[1:],
                                                                     strict=False)), line


@pytest.mark.slow
def test_default_scene_converges(record_property) -> None:
    check_converges("default", CONVERGING_SIZES, "cpu", record_property)


@pytest.mark.slow
def test_lightly_damped_scene_converges(record_property) -> None:
    check_converges("light", CONVERGING_SIZES, "cpu", record_property)


def test_point_supports_drift_logarithmically(record_property) -> None:
    """Documentation: held by single nodes (grip_radius 0), the sag and the ball's lowest
    point change by about the same length at each halving of the spacing (a log(1 / L)
    drift, the point supports'), and that length is a few mm: a tenth of what the per-node
    units moved the ball's rebound by. With the default's grip the sag converges
    (``CONVERGING``). Of the ``springs`` cloth (module doc): with the bending stiffness the
    lowest point also moves by the bending's own change over these grids (-2.7, -0.2 mm
    at n = 13, 25, 49 with point supports; docs/accuracy.md)."""
    runs = [run("point", n, "cpu") for n in CPU_SIZES]
    for q in LOGARITHMIC:
        c = convergence(runs, q)
        line = line_of("point", c)
        print(line)
        record_property(q, line)
        a, b = (abs(d) for d in c.differences)
        assert 0.6 < b / a < 1.4, line
    rebound = convergence([run("per_node", n, "cpu") for n in CPU_SIZES], "rebound_m")
    sag = convergence(runs, "sag_m")
    assert min(abs(d) for d in rebound.differences) > 10 * max(abs(d) for d in sag.differences)


def rebounds(names: tuple[str, ...], sizes: tuple[int, ...], record_property
             ) -> dict[str, Convergence]:
    """Each cloth's rebound over ``sizes`` on the CPU, recorded."""
    out = {}
    for name in names:
        out[name] = convergence([run(name, n, "cpu") for n in sizes], "rebound_m")
        line = line_of(name, out[name])
        print(line)
        record_property(name, line)
    return out


def test_per_node_parameters_drift(record_property) -> None:
    """Documentation of issue 30's table: with the per-node values fixed, the ball's rebound
    changes between grids by several times what it does in material units (the damping
    rate grows as n^2 and the contact stiffness with the nodes covered). Of the ``springs``
    cloth, which the issue measured (module doc)."""
    c = rebounds(("per_node", "springs"), CPU_SIZES, record_property)
    change = {name: abs(c[name].differences[-1]) for name in c}
    assert change["per_node"] > 5 * change["springs"], change


@pytest.mark.slow
def test_a_bending_stiffness_makes_the_rebound_converge(record_property) -> None:
    """The default's rebound converges on n = 13-97 (CPU float64, about a minute): its
    successive differences shrink, where the same cloth with the bending springs alone
    turns at n = 97 (the difference from 49 to 97 larger than from 25 to 49). The springs'
    resistance to bending is geometric and fades as L^4 at a given curvature; the bending
    stiffness resists alike at every n, and takes over from them between n = 25 and 97."""
    c = rebounds(("default", "springs"), (*CPU_SIZES, 97), record_property)
    assert c["default"].shrinking(), line_of("default", c["default"])
    springs = [abs(d) for d in c["springs"].differences]
    assert springs[-1] > springs[-2], springs


@pytest.mark.gpu
@pytest.mark.parametrize("name", ["default", "light"])
def test_converges_on_the_larger_range(name: str, cuda: str, record_property) -> None:
    check_converges(name, GPU_SIZES, cuda, record_property)
    runs = [run(name, n, cuda) for n in GPU_SIZES]
    for q in QUANTITIES:  # every quantity's values and orders, for the record
        line = line_of(name, convergence(runs, q))
        print(line)
        record_property(f"{name}.{q}", line)


def test_landing_is_where_the_ball_meets_the_cloth_at_rest() -> None:
    """The landing is read against the cloth at rest, which the ball meets before any
    damping acts: the default and its lightly damped variant land at the same time (read
    from the moved cloth, a node pushed out within its first frame of contact hid the
    landing for a frame or more: 295.9 against 299.3 ms at n = 25). The frame of the
    crossing ends after the contact began, which the two dampings answer apart: a
    microsecond between them, a thousandth of a frame."""
    for n in CPU_SIZES:
        a, b = (run(name, n, "cpu").quantities["landing_s"] for name in ("default", "light"))
        assert a == pytest.approx(b, abs=1e-6), (n, a, b)
