"""The plate bending term (``cloth.bending_stiffness`` D, N m; the ``bend`` effect's term
beside its springs) against the NumPy float64 oracle and against the plate equation.

The term is the quadratic energy D/2 |grad grad x|^2 on the grid (second differences
along rows and columns, the mixed one on each cell; native/core/forces.hpp: plate_sum),
k = D / L^2 a stencil, derived in native/core (per_node) and on its own by the oracle
(oracle.node_plate_stiffness, plate_force: the stencils' transposes applied in NumPy). Its
force is linear in the positions: on a sinusoidal sheet w = A sin(kx x) cos(kz z) the
interior nodes feel exactly -(D / L^2) L^4 (lx + lz)^2 w, l = (2 sin(k L / 2) / L)^2, whose
limit is the plate's -D (kx^2 + kz^2)^2 w per area, approached at second order.
"""

from __future__ import annotations

import numpy as np
import pytest
from clothball.game import Cloth, ReferenceCloth, Scene
from clothball.game.sim.config import node_values
from clothball.game.sim.oracle import (
    node_plate_stiffness,
    plate_diagonal,
    plate_energy,
    plate_force,
)
from clothball.game.sim.scene import mass_weights
from clothball.game.sim.stability import node_stiffness
from clothball.game.study.energy import total_energy
from clothball.game.study.integrators_ref import Linearization

EPS = float(np.finfo(np.float64).eps)
D = 2e-3  # N m
KX, KZ, AMP = 2 * np.pi * 1.3, 2 * np.pi * 0.7, 0.01  # 1/m, 1/m, m


def plate_scene(n: int, d: float = D, **cloth: float) -> Scene:
    return Scene.from_dict({
        "cloth": {"n": n, "k_bend": 0.0, "bending_stiffness": d, **cloth},
        "sim": {"effects": ["bend"], "substeps": 1, "precision": "float64"},
    })


def sinusoid(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The rest grid with y raised by w = A sin(kx x + 0.3) cos(kz z + 0.1); (positions, w)."""
    pos = ReferenceCloth(scene).pos.copy()
    w = AMP * np.sin(KX * pos[..., 0] + 0.3) * np.cos(KZ * pos[..., 2] + 0.1)
    pos[..., 1] += w
    return pos, w


def engine_force(scene: Scene, backend: str, pos: np.ndarray) -> np.ndarray:
    """The force on every node at ``pos`` (at rest): one substep's velocity times m / dt."""
    cloth = Cloth(scene, backend=backend, precision="float64")
    cloth.set_state(pos, np.zeros_like(pos))
    cloth.step(1)
    return cloth.velocities() * scene.node_masses / float(scene["sim"]["frame_dt"])


def rounding_bound(scene: Scene, pos: np.ndarray) -> float:
    """What rounding the positions alone may move a node's plate force by: 64 k (the
    stencil's absolute coefficients) times a few eps of the largest coordinate."""
    return 4 * 64 * node_plate_stiffness(scene) * EPS * float(np.abs(pos).max())


@pytest.mark.parametrize("n", [2, 5, 16, 48, 131])
def test_engine_and_oracle_derive_the_same_stiffness(n: int) -> None:
    s = plate_scene(n, size=0.8)
    assert node_values(s).plate_k == pytest.approx(node_plate_stiffness(s), rel=1e-14)
    assert node_plate_stiffness(s) == pytest.approx(D / (0.8 / (n - 1)) ** 2, rel=1e-14)


def test_no_bending_stiffness_no_plate_term() -> None:
    """The schema's default (0) and scenes without it: k 0 (the bend springs alone)."""
    springs_only = Scene.from_dict({"cloth": {"n": 9, "k_bend": 20.0},
                                    "sim": {"effects": ["structural", "bend"]}})
    for s in (springs_only, plate_scene(9, 0.0)):
        assert node_values(s).plate_k == 0.0 == node_plate_stiffness(s)


@pytest.mark.parametrize("n", [4, 9, 33])
def test_force_of_a_sinusoid(backend: str, n: int) -> None:
    """Every node (the border's fewer stencils too) against the oracle; the interior (two
    nodes in from the border) against the discrete plate equation, exactly."""
    s = plate_scene(n)
    pos, w = sinusoid(s)
    got = engine_force(s, backend, pos)
    want = plate_force(pos, node_plate_stiffness(s))
    tol = rounding_bound(s, pos) + 8 * EPS * float(np.abs(want).max())
    np.testing.assert_allclose(got, want, rtol=0, atol=tol)
    L = s.rest_length
    lx, lz = ((2 * np.sin(k * L / 2) / L) ** 2 for k in (KX, KZ))
    exact = -D * L**2 * (lx + lz) ** 2 * w
    inner = np.s_[2:-2, 2:-2]
    if n > 4:
        np.testing.assert_allclose(got[inner][..., 1], exact[inner], rtol=0, atol=tol)
        # No in-plane force on a sheet moved only out of its plane (interior).
        np.testing.assert_allclose(got[inner][..., [0, 2]], 0.0, rtol=0, atol=tol)


def test_force_tends_to_the_plate_equation() -> None:
    """The interior force per area against -D (kx^2 + kz^2)^2 w: the error is the
    stencil's (k L)^2 / 6 each direction, second order, shrinking 4x a halving."""
    errors = []
    for n in (17, 33, 65, 129):
        s = plate_scene(n)
        pos, w = sinusoid(s)
        got = plate_force(pos, node_plate_stiffness(s))[2:-2, 2:-2, 1] / s.rest_length**2
        want = -D * (KX**2 + KZ**2) ** 2 * w[2:-2, 2:-2]
        errors.append(float(np.abs(got - want).max() / np.abs(want).max()))
    L = 1.0 / 16
    assert errors[0] < (max(KX, KZ) * L) ** 2 / 6 * 1.05, errors
    ratios = [a / b for a, b in zip(errors, errors[1:], strict=False)]
    assert all(3.8 < r < 4.2 for r in ratios), (errors, ratios)


@pytest.mark.parametrize("n", [3, 12])
def test_rigid_motions_feel_nothing(backend: str, n: int) -> None:
    """Each stencil annihilates a plane: the flat sheet turned and moved anywhere (and
    stretched within its plane) has no plate force, only rounding."""
    s = plate_scene(n, 0.5)
    rest = ReferenceCloth(s).pos
    a, b = 0.7, -1.1
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]) @ \
        np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    for pos in (rest, rest @ rot.T + [0.3, -2.0, 1.5], 1.3 * rest @ rot.T):
        got = engine_force(s, backend, pos)
        np.testing.assert_allclose(got, 0.0, rtol=0, atol=rounding_bound(s, pos))
        np.testing.assert_allclose(plate_force(pos, 1.0), 0.0,
                                   atol=4 * 64 * EPS * float(np.abs(pos).max()))


def test_force_is_minus_the_energy_gradient() -> None:
    """The oracle's force against central differences of its energy (the energy the
    accuracy study's references add, ``total_energy``), and a cylinder's energy: a sheet
    rolled without stretching to curvature c holds D/2 c^2 per area (the rows' stencils
    see the whole bend)."""
    s = plate_scene(7, 0.03)
    k = node_plate_stiffness(s)
    rng = np.random.default_rng(4)
    pos = ReferenceCloth(s).pos + 0.02 * rng.standard_normal((7, 7, 3))
    f = plate_force(pos, k)
    h = 1e-6
    for idx in [(0, 0, 1), (0, 3, 0), (3, 3, 2), (6, 5, 1), (1, 2, 0)]:
        e = np.zeros_like(pos)
        e[idx] = h
        grad = (total_energy(s, pos + e, np.zeros_like(pos))
                - total_energy(s, pos - e, np.zeros_like(pos))) / (2 * h)
        assert -grad == pytest.approx(f[idx], rel=1e-7, abs=1e-9)
    n, c = 65, 2.0
    s = plate_scene(n, 0.03)
    L = s.rest_length
    theta = (np.arange(n) - (n - 1) / 2) * L * c
    pos = np.zeros((n, n, 3))
    pos[..., 0] = np.sin(theta)[None, :] / c
    pos[..., 1] = (1 - np.cos(theta))[None, :] / c
    pos[..., 2] = (np.arange(n) * L)[:, None]
    rows = n * (n - 2) * L**2  # the area the row triples stand for
    want = 0.5 * 0.03 * c**2 * rows
    # A chord's second difference is 2 (1 - cos(c L)) / c: (c L)^2 (1 - (c L)^2 / 12).
    assert plate_energy(pos, node_plate_stiffness(s)) == pytest.approx(want, rel=(c * L) ** 2 / 5)


def test_jacobian_is_the_force_and_its_diagonal() -> None:
    """The implicit integrator's reference Jacobian of the plate term is the (linear) force
    itself, and the preconditioner's diagonal is its diagonal: k 20 inside, 4 at a corner."""
    s = plate_scene(8, 0.01)
    k = node_plate_stiffness(s)
    rng = np.random.default_rng(5)
    pos = ReferenceCloth(s).pos + 0.01 * rng.standard_normal((8, 8, 3))
    lin = Linearization(s, pos, np.zeros(3))
    w = rng.standard_normal(pos.shape)
    jw, _ = lin.jvp(w, np.zeros(3))
    np.testing.assert_allclose(jw, plate_force(w, k), rtol=0, atol=1e-12 * np.abs(jw).max())
    dn, _ = lin.neg_diag()
    for idx in [(0, 0), (0, 3), (1, 1), (4, 4), (7, 6)]:
        e = np.zeros_like(pos)
        e[idx] = 1.0
        assert -lin.jvp(e, np.zeros(3))[0][idx][1] == pytest.approx(dn[idx][1], rel=1e-14)
    assert dn[4, 4, 0] == pytest.approx(20 * k) and dn[0, 0, 2] == pytest.approx(4 * k)
    np.testing.assert_array_equal(plate_diagonal(8, k)[..., None] * np.ones(3), dn)


def test_the_stability_bound_covers_the_plate() -> None:
    """The stability bound counts 64 k a node inside (Gershgorin: 20 + 4 x 8 + 4 x 2 + 4 x 1)
    and, per unit of mass (masses by area: 1/2 on an edge, 1/4 at a corner), 72 k at the
    border, its largest: the largest eigenvalue of k W^-1 B^T B (W the mass weights) is
    within it and near it."""
    n = 24
    s = plate_scene(n, 0.01)
    k = node_plate_stiffness(s)
    basis = np.eye(n * n).reshape(n * n, n, n, 1)
    cols = np.stack([-plate_force(b, 1.0)[..., 0].ravel() for b in basis], axis=1)
    w = np.sqrt(mass_weights(n).ravel())
    top = float(np.linalg.eigvalsh(cols / w[:, None] / w[None, :]).max())
    assert 0.85 * 72 < top <= 72 * (1 + 1e-12)
    assert node_stiffness(s) == pytest.approx(72 * k)


def test_the_plate_changes_the_motion() -> None:
    """Stepped on the engine, a bent sheet with a bending stiffness springs back where one
    without it does not (the term is on in the kernels, not only in the oracle)."""
    s = plate_scene(9, 0.05)
    pos, _ = sinusoid(s)
    flat = s.with_changes({"cloth": {"bending_stiffness": 0.0}})
    moved = []
    for scene in (s, flat):
        cloth = Cloth(scene, backend="cpu", precision="float64")
        cloth.set_state(pos, np.zeros_like(pos))
        cloth.step(20)
        moved.append(float(np.abs(cloth.positions() - pos).max()))
    assert moved[1] == 0.0 and moved[0] > 1e-4, moved
