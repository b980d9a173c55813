"""Both backends against the NumPy float64 oracle, every effect, both precisions.

Tolerances are derived, not guessed: the oracle itself is run twice, once from a state
perturbed by one rounding error of the precision under test (eps * |x| on every
coordinate). How far those two oracle runs drift apart is how far two correct
implementations that round differently may drift; the backend must stay within 10x that
drift plus 10 eps of the largest coordinate.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from clothball import _native
from clothball.game import Cloth, ReferenceCloth, Scene

FRAMES = 40  # x the automatic substeps (2-6 here)

# A free net struck by the ball (or held by strain limiting alone) is sensitive to its
# start, the more so with the cell-assembled border (lighter border nodes, border springs
# at half k): two oracles a float32 rounding apart spread so far in 40 frames that the
# motion is only 22-75 tolerances, where the check below asks for 100. In 30 frames it is
# 130-766 (`python tools/lab/oracle_spread.py`), so these runs end while the comparison
# still means something.
CASE_FRAMES = {"ball": 30, "ball_edges": 30, "ball_lands": 30, "strain_limit": 30,
               "material_ball": 30, "material_ball_edges": 30}

BASE = {"cloth": {"n": 14, "size": 0.5, "height": 1.0}}


def scene_with(effects: list[str], **extra: dict) -> Scene:
    d = {"cloth": dict(BASE["cloth"]), "sim": {"effects": effects}}
    for section, table in extra.items():
        d.setdefault(section, {}).update(table)
    return Scene.from_dict(d)


CASES = {
    "structural": (["structural", "gravity"], {}),
    "structural_two_sided": (["structural", "gravity"], {"cloth": {"structural_two_sided": True}}),
    "shear": (["structural", "shear", "gravity"], {"cloth": {"k_shear": 400.0}}),
    "bend": (["structural", "bend", "gravity"], {"cloth": {"k_bend": 100.0}}),
    "gravity_only": (["gravity"], {}),
    "damping": (["structural", "gravity", "damping"], {"cloth": {"damping": 0.01}}),
    "ball": (
        ["structural", "gravity", "ball"],
        {"ball": {"position": [0.03, 1.085, -0.02], "velocity": [0.0, -0.3, 0.0]}},
    ),
    # Edge contact: the ball comes down onto the middle of a spring between two nodes.
    "ball_edges": (
        ["structural", "gravity", "ball"],
        {"ball": {"position": [0.03, 1.085, -0.02], "velocity": [0.0, -0.3, 0.0],
                  "contact": "edges"}},
    ),
    "coupling": (["structural", "gravity", "coupling"], {}),
    # The ball starts clear of the cloth (contact compiled out) and lands during the run.
    "ball_lands": (
        ["structural", "gravity", "damping", "ball", "coupling"],
        {"ball": {"position": [0.01, 1.1, 0.0], "velocity": [0.0, -2.0, 0.0]}},
    ),
    "all": (
        ["structural", "shear", "bend", "gravity", "damping", "ball", "coupling"],
        {"ball": {"position": [0.0, 1.085, 0.0], "velocity": [0.0, -0.3, 0.0]}},
    ),
    "wind": (
        ["structural", "gravity", "wind"],
        {"wind": {"velocity": [1.0, -0.8, 0.5], "lift": 0.5}},
    ),
    "strain_limit": (
        ["structural", "gravity", "coupling", "strain_limit"],
        {"strain_limit": {"max_strain": 0.002, "iterations": 4}},
    ),
    # Material values (independent of n): the engine derives beta1 and k_b from them
    # (native per_node), the oracle on its own (oracle.node_damping, node_contact_stiffness).
    "material_damping": (["structural", "gravity", "damping"], {"cloth": {"damping_rate": 4.0}}),
    "material_ball": (
        ["structural", "gravity", "damping", "ball"],
        {"cloth": {"damping_rate": 4.0}, "ball": {
            "stiffness_per_area": 3.4e6, "position": [0.03, 1.085, -0.02],
            "velocity": [0.0, -0.3, 0.0]}},
    ),
    "material_ball_edges": (
        ["structural", "gravity", "ball"],
        {"ball": {"stiffness_per_area": 3.4e6, "position": [0.03, 1.085, -0.02],
                  "velocity": [0.0, -0.3, 0.0], "contact": "edges"}},
    ),
    # The plate bending term (cloth.bending_stiffness): instead of the bend springs, and
    # beside them with every other effect (the oracle derives k = D / L^2 on its own).
    "plate": (["structural", "bend", "gravity", "coupling"],
              {"cloth": {"k_bend": 0.0, "bending_stiffness": 0.02}}),
    "plate_all": (
        ["structural", "shear", "bend", "gravity", "damping", "ball", "coupling"],
        {"cloth": {"bending_stiffness": 0.02, "damping_rate": 4.0},
         "ball": {"position": [0.0, 1.085, 0.0], "velocity": [0.0, -0.3, 0.0]}},
    ),
    # 1600 nodes: several GPU blocks, so the cross-block ball force sum is exercised.
    "all_large": (
        ["structural", "shear", "bend", "gravity", "damping", "ball", "coupling"],
        {"cloth": {"n": 40, "size": 1.0, "structural_two_sided": True},
         "ball": {"position": [0.01, 1.085, 0.0], "velocity": [0.0, -0.3, 0.0]}},
    ),
}

# Hands moved a few millimetres: enough to drive the coupling, gentle enough that the
# motion is smooth and rounding errors are not amplified chaotically.
HIPS_MOVE = 0.2 * np.array(
    [[0.02, 0.03, -0.01], [0.0, -0.02, 0.01], [-0.01, 0.01, 0.0], [0.0, 0.0, 0.02]]
)


def _drive(sim, scene: Scene, frames: int, substeps: int, hips: np.ndarray) -> None:
    if isinstance(sim, Cloth):
        sim.set_hips(hips)
        sim.step(frames)
    else:
        sim.hips = hips
        sim.step(frames, substeps)


def _state(sim) -> np.ndarray:
    if isinstance(sim, Cloth):
        pos, vel = sim.positions(), sim.velocities()
        bp, bv = sim.ball()
    else:
        pos, vel, bp, bv = sim.pos, sim.vel, sim.ball_pos, sim.ball_vel
    return np.concatenate([pos.ravel(), vel.ravel(), bp, bv])


def allowed_drift(scene: Scene, precision: str, substeps: int, hips: np.ndarray,
                  make: Callable[[Scene], ReferenceCloth] = ReferenceCloth,
                  drive: Callable[[ReferenceCloth], None] | None = None) -> float:
    """The tolerance of the module doc, for the reference that ``make`` builds, driven by
    ``drive`` (default: FRAMES frames with the hands at ``hips``)."""
    eps = float(np.finfo(np.float32 if precision == "float32" else np.float64).eps)
    rng = np.random.default_rng(7)
    a, b = make(scene), make(scene)
    b.pos = b.pos * (1 + eps * rng.choice([-1.0, 1.0], size=b.pos.shape))
    b.ball_pos = b.ball_pos * (1 + eps * rng.choice([-1.0, 1.0], size=3))
    for sim in (a, b):
        if drive is None:
            _drive(sim, scene, FRAMES, substeps, hips)
        else:
            drive(sim)
    drift = np.abs(_state(a) - _state(b)).max()
    scale = np.abs(_state(a)).max()
    return 10 * drift + 10 * eps * scale


@pytest.mark.parametrize("case", list(CASES))
def test_matches_oracle(case: str, backend: str, precision: str) -> None:
    effects, extra = CASES[case]
    check_against_oracle(case, scene_with(effects, **extra), backend, precision)


def check_against_oracle(case: str, scene: Scene, backend: str, precision: str,
                         frames: int | None = None, normals: bool = True) -> Cloth:
    """``frames`` frames (default: the case's, CASE_FRAMES or FRAMES) of the scene on the
    backend against the oracle, with the hands moved (HIPS_MOVE), and the normals (their
    bound is these small cloths'); returns the cloth."""
    if frames is None:
        frames = CASE_FRAMES.get(case, FRAMES)
    cloth = Cloth(scene, backend=backend, precision=precision)
    ref = ReferenceCloth(scene)
    hips = ref.hips + HIPS_MOVE
    _drive(cloth, scene, frames, cloth.substeps, hips)
    _drive(ref, scene, frames, cloth.substeps, hips)
    tol = allowed_drift(scene, precision, cloth.substeps, hips,
                        drive=lambda sim: _drive(sim, scene, frames, cloth.substeps, hips))
    got, want = _state(cloth), _state(ref)
    assert np.all(np.isfinite(got))
    err = np.abs(got - want).max()
    assert err <= tol, f"{case} {backend} {precision}: max error {err:.3g} > allowed {tol:.3g}"
    # The run did something: the state moved well beyond the tolerance.
    assert np.abs(want - _state(ReferenceCloth(scene))).max() > 100 * tol
    np.testing.assert_allclose(cloth.corner_forces(), ref.corner_forces(), rtol=0, atol=2000 * tol)
    if normals:
        atol = 1e-3 if precision == "float32" else 1e-8
        np.testing.assert_allclose(cloth.normals(), ref.normals(), rtol=0, atol=atol)
    return cloth


@pytest.mark.gpu
@pytest.mark.parametrize("case", ["ball_lands", "all_large", "strain_limit"])
def test_cuda_node_a_thread_matches_oracle(
    case: str, cuda: str, precision: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The CUDA launch shape of the largest cloths (a node a thread, the ball's update a
    launch of its own), forced on small ones: same oracle and tolerance as above."""
    monkeypatch.setenv("CLOTHBALL_CUDA_NODE_A_THREAD", "1")
    test_matches_oracle(case, cuda, precision)


@pytest.mark.gpu
@pytest.mark.parametrize("case", ["ball", "ball_edges", "ball_lands", "coupling", "all",
                                  "all_large"])
def test_cuda_tiled_matches_oracle(
    case: str, cuda: str, precision: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The tiled frame (the whole frame in one launch, a tile a block, the state on chip),
    forced on small cloths, where the tiles are a few nodes and every node is some tile's
    border or halo: same oracle and tolerance as above."""
    monkeypatch.setenv("CLOTHBALL_CUDA_TILED", "1")
    effects, extra = CASES[case]
    cloth = check_against_oracle(case, scene_with(effects, **extra), cuda, precision)
    assert cloth.engine_path == "tiled"


# How deep the ball starts in the cloth's middle, per scene: enough for the contact to slow
# it by several mm/s in one frame where the tiled frame starts (TILED_MIN_N, 512; the
# default's TILED_MIN_N_BEND, 320). Both scenes' contact stiffness is per
# contact area (docs/scenes.md): classic's 17.4e6 N/m^3 is 67 N/m a node at n = 512 (the
# paper's 5000 N/m a node at its n = 60), the default's 11.0e6 N/m^3 42 N/m a node, and the
# force grows about as the depth squared (deeper, more nodes press harder). Measured with
# the CPU backend, float64, for one frame with the hands moved as below: classic sunk
# 0.5 mm slows the ball by 0.99 mm/s (under the 1 mm/s this test asks, which is why it
# failed there), 1 mm by 3.8, 1.5 mm by 8.4, 2 mm by 14.7; the default (bending stiffness
# 2 mN m) sunk 0.5 mm by 0.87 mm/s, 1.5 mm by 6.9 (0.82 and 6.8 with 0.5 mN m; at n = 320
# with the cell-assembled border 0.87 and 6.87: contact per area is the same at any n). Before
# issue 42, classic's 5000 N/m a node slowed it by 8.6 mm/s sunk 0.5 mm. Sunk 1.5 mm, both
# scenes' CPU backend stays within the oracle's derived tolerance (check_against_oracle
# on "cpu").
SINK = {"classic": 1.5e-3, "default": 1.5e-3}


@pytest.mark.gpu
@pytest.mark.parametrize("scene_name", ["classic", "default"])
def test_cuda_tiled_where_chosen_matches_oracle(
    scene_name: str, cuda: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The tiled frame where it is chosen by itself (the smallest such n), the ball sunk
    into the cloth's middle (SINK) and coming down, the corners pulled, for a frame (the
    oracle's NumPy substep takes ~0.2 s at this n): same oracle and tolerance as above, in
    float64. In float32 the derived tolerance says nothing after one frame here:
    the pulled corners, light at this n, make the oracle's own drift 0.3 m/s against 18 m/s
    of motion (NumPy reference, n = 384), so float32 is checked on small cloths above
    (test_cuda_tiled_matches_oracle). The normals, a kernel of their own over the state,
    are left to the small cases too: their fixed bound is for those cloths' spacing."""
    monkeypatch.delenv("CLOTHBALL_CUDA_TILED", raising=False)
    base = Scene.load(scene_name)
    top = base["cloth"]["height"] + base["ball"]["radius"] - SINK[scene_name]
    least = _native.TILED_MIN_N_BEND if "bend" in base.effects else _native.TILED_MIN_N
    scene = base.with_changes({"cloth": {"n": least},
                               "ball": {"position": [0.0, top, 0.0],
                                        "velocity": [0.0, -0.1, 0.0]}})
    cloth = check_against_oracle(scene_name, scene, cuda, "float64", frames=1, normals=False)
    assert cloth.engine_path == "tiled"
    # The cloth held the ball up: slower than free fall by more than 1 mm/s (the nodes
    # under it, light at this n, are pushed away within the frame, so contact comes and goes).
    free_fall = -0.1 + scene["sim"]["gravity"][1] * cloth.frame_dt
    assert cloth.ball()[1][1] > free_fall + 1e-3


def test_normals_of_a_known_surface(backend: str) -> None:
    """A cloth bent into the plane y = x tan(a) has normal (-sin a, cos a, 0) everywhere."""
    scene = scene_with(["structural"])
    cloth = Cloth(scene, backend=backend, precision="float64")
    a = 0.3
    pos = ReferenceCloth(scene).pos.copy()
    pos[..., 1] = pos[..., 0] * np.tan(a)
    cloth.set_state(pos, np.zeros_like(pos))
    nrm = cloth.normals()
    want = np.broadcast_to([-np.sin(a), np.cos(a), 0.0], nrm.shape)
    np.testing.assert_allclose(nrm, want, atol=1e-12)


def test_free_fall_is_exact(backend: str, precision: str) -> None:
    """Gravity alone: semi-implicit Euler gives y_k = y0 - g dt^2 k(k+1)/2 exactly."""
    scene = scene_with(["gravity"], sim={"substeps": 4})
    cloth = Cloth(scene, backend=backend, precision=precision)
    cloth.step(25)
    k = 25 * 4
    dt = cloth.dt
    y = 1.0 - 9.81 * dt * dt * k * (k + 1) / 2
    rtol = 1e-5 if precision == "float32" else 1e-12
    np.testing.assert_allclose(cloth.positions()[..., 1], y, rtol=rtol)
    np.testing.assert_allclose(cloth.velocities()[..., 1], -9.81 * dt * k, rtol=rtol)
