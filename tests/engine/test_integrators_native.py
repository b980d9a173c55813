"""The engine's velocity Verlet and implicit Euler (both backends) against the NumPy float64
reference integrators (``game/integrators_ref.py``), every effect each supports.

Tolerance: derived as in ``test_engine_vs_oracle`` (the reference run twice, once from a
state perturbed by one float64 rounding; 10x that drift plus 10 eps of the largest value).
Velocity Verlet is compared as is. Implicit Euler is compared twice: with CG cut at a fixed
iteration count and no tolerance (both sides then do the same arithmetic, so only rounding
separates them), and with CG converged to 1e-12 (the early exit on tolerance is then taken
on both sides; its iteration count may differ by one where the residual lands on the
tolerance, which moves dv by about 1e-12 of itself: far inside the bound).
The hands move in the middle of each run, so Verlet's kept force must be recomputed.

Implicit Euler starts from the cloth stretched by 0.2 %: at rest every tension-only spring
sits exactly at its kink (length L), where the linearised step is discontinuous (the axial
stiffness jumps from 0 to k), so one rounding there picks a different Newton step and the
derived tolerance becomes as large as the motion itself. Off the kink the step is smooth.
"""

from __future__ import annotations

import numpy as np
import pytest
from clothball.game import Cloth, Scene, SceneError
from clothball.game.sim.stability import auto_substeps, stable_dt
from clothball.game.study.integrators_ref import IntegratingCloth

from tests.engine.test_engine_vs_oracle import (
    CASES,
    FRAMES,
    HIPS_MOVE,
    _drive,
    _state,
    allowed_drift,
    scene_with,
)

SUPPORTED = {
    "velocity_verlet": [c for c in CASES if c != "strain_limit"],
    # Implicit Euler's Jacobian linearises node contact only: edge contact is refused.
    "implicit_euler": [c for c in CASES
                       if c not in ("strain_limit", "ball_edges", "material_ball_edges")],
}
CG = {"fixed": {"cg_tolerance": 0.0, "cg_max_iterations": 12},
      "converged": {"cg_tolerance": 1e-12, "cg_max_iterations": 2000}}
PARAMS = [(i, c, cg) for i, cases in SUPPORTED.items() for c in cases
          for cg in (CG if i == "implicit_euler" else ["-"])]


def _scene(case: str, integrator: str, cg: str) -> Scene:
    effects, extra = CASES[case]
    scene = scene_with(effects, **extra)
    sim = {"integrator": integrator, **CG.get(cg, {})}
    return scene.with_changes({"sim": sim})


def _start(integrator: str, pos: np.ndarray) -> np.ndarray:
    if integrator != "implicit_euler":
        return pos
    centre = pos.mean(axis=(0, 1))
    return centre + 1.002 * (pos - centre)


def _reference(integrator: str, cg: str):  # noqa: ANN202 - a factory of IntegratingCloth
    opts = CG.get(cg, {})

    def make(s: Scene) -> IntegratingCloth:
        ic = IntegratingCloth(s, integrator, cg_tol=opts.get("cg_tolerance", 1e-10),
                              cg_max_iter=opts.get("cg_max_iterations", 2000))
        ic.pos = _start(integrator, ic.pos)
        return ic

    return make


def _drive_twice(sim, scene: Scene, substeps: int, hips: np.ndarray) -> None:
    half = FRAMES // 2
    _drive(sim, scene, half, substeps, hips)
    _drive(sim, scene, FRAMES - half, substeps, hips + 0.5 * HIPS_MOVE[::-1])


@pytest.mark.parametrize(("integrator", "case", "cg"), PARAMS)
def test_matches_reference(integrator: str, case: str, cg: str, backend: str) -> None:
    scene = _scene(case, integrator, cg)
    make = _reference(integrator, cg)
    cloth = Cloth(scene, backend=backend, precision="float64")
    ref = make(scene)
    cloth.set_state(ref.pos, ref.vel)
    hips = ref.hips + HIPS_MOVE
    _drive_twice(cloth, scene, cloth.substeps, hips)
    _drive_twice(ref, scene, cloth.substeps, hips)
    tol = allowed_drift(scene, "float64", cloth.substeps, hips, make,
                        lambda sim: _drive_twice(sim, scene, cloth.substeps, hips))
    got, want = _state(cloth), _state(ref)
    assert np.all(np.isfinite(got))
    err = np.abs(got - want).max()
    assert err <= tol, f"{integrator} {case} {cg} {backend}: max error {err:.3g} > {tol:.3g}"
    assert np.abs(want - _state(make(scene))).max() > 100 * tol  # the run did something
    np.testing.assert_allclose(cloth.corner_forces(), ref.corner_forces(), rtol=0, atol=2000 * tol)


def test_edge_contact_refused_by_implicit_euler() -> None:
    with pytest.raises(SceneError, match="ball.contact"):
        Scene.from_dict({"cloth": {"n": 5}, "ball": {"contact": "edges"}, "sim": {
            "integrator": "implicit_euler", "effects": ["structural", "ball"]}})


def test_strain_limit_needs_semi_implicit_euler() -> None:
    for integ in ("velocity_verlet", "implicit_euler"):
        with pytest.raises(SceneError, match="sim.integrator"):
            Scene.from_dict({"cloth": {"n": 5}, "sim": {
                "integrator": integ, "effects": ["structural", "strain_limit"]}})


@pytest.mark.parametrize(("key", "value"), [("cg_max_iterations", 0), ("cg_tolerance", -1.0),
                                            ("cg_tolerance", float("nan"))])
def test_cg_keys_are_checked(key: str, value: float) -> None:
    with pytest.raises(SceneError, match=f"sim.{key}"):
        Scene.from_dict({"cloth": {"n": 5}, "sim": {key: value}})


def test_substep_bounds_per_integrator() -> None:
    """Verlet's bound leaves its (implicit) damping out, so it is at least semi-implicit
    Euler's; implicit Euler without a ball takes one substep a frame at any stiffness."""
    stiff = {"cloth": {"n": 30, "k_structural": 2e5, "damping": 0.05},
             "sim": {"effects": ["structural", "gravity", "damping", "coupling"]}}
    se = Scene.from_dict(stiff)
    vv = se.with_changes({"sim": {"integrator": "velocity_verlet"}})
    ie = se.with_changes({"sim": {"integrator": "implicit_euler"}})
    assert stable_dt(vv) >= stable_dt(se)
    assert auto_substeps(se) > 10 and auto_substeps(ie) == 1
