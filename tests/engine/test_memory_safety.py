"""Guards for the CPU engine's indexing on small and odd cloths, checked without a sanitizer.

The CPU sweep splits every row into border nodes (bounds-tested) and interior nodes (no
bounds tests, two nodes from every edge), and the ball tracking reads each row again: on
cloths of n = 2..5 the interior is empty or one node wide, and n = 17 leaves a vector
remainder. A neighbour index that strayed out of the grid would read or write another
plane of the double buffer (or past it), so the float64 engine is compared with the NumPy
oracle node by node, after frames that move every node, with the ball resting inside the
cloth (every node and edge in contact) in both contact modes. The native build with
``-C cmake.define.CLOTHBALL_SANITIZE=address`` runs the same cases under AddressSanitizer
(see native/CMakeLists.txt).
"""

from __future__ import annotations

import numpy as np
import pytest
from clothball.game import Cloth, ReferenceCloth, Scene

ALL = ["structural", "shear", "bend", "gravity", "damping", "ball", "coupling", "wind"]
EFFECT_SETS = {
    "all": ALL,
    "all_strain": [*ALL, "strain_limit"],
    "tiny_server": ["structural", "gravity", "damping", "ball", "coupling"],
}
FRAMES = 5


def scene_for(n: int, effects: list[str], contact: str, **sim: object) -> Scene:
    d: dict = {
        "cloth": {"n": n, "size": 0.5, "height": 1.0, "structural_two_sided": True},
        "sim": {"effects": effects, "precision": "float64", **(sim or {"substeps": 20})},
        # Large enough to cover the whole cloth, centred just above it: every node inside.
        "ball": {"position": [0.01, 1.05, -0.02], "velocity": [0.0, -0.5, 0.0],
                 "radius": 0.4, "stiffness": 50.0, "contact": contact},
    }
    if "wind" in effects:
        d["wind"] = {"velocity": [1.0, -0.8, 0.5], "lift": 0.5}
    if "strain_limit" in effects:
        d["strain_limit"] = {"max_strain": 0.01, "iterations": 3}
    return Scene.from_dict(d)


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("contact", ["nodes", "edges"])
@pytest.mark.parametrize("effects", list(EFFECT_SETS))
@pytest.mark.parametrize("n", [2, 3, 4, 5, 17])
def test_small_cloths_match_the_oracle(n: int, effects: str, contact: str, threads: int) -> None:
    scene = scene_for(n, EFFECT_SETS[effects], contact)
    cloth = Cloth(scene, backend="cpu", threads=threads)
    ref = ReferenceCloth(scene)
    hips = ref.hips + 0.01 * np.array([[1, 2, -1], [0, -2, 1], [-1, 1, 0], [0, 0, 2]])
    cloth.set_hips(hips)
    ref.hips = hips
    assert cloth.substeps == 20
    cloth.step(FRAMES)
    ref.step(FRAMES, 20)
    pos, vel = cloth.positions(), cloth.velocities()
    bp, bv = cloth.ball()
    assert np.all(np.isfinite(pos)) and np.all(np.isfinite(vel))
    # Every node moved (the cases exercise every node's neighbours), and agrees with the
    # oracle to float64 rounding.
    assert np.all(np.abs(ref.pos - ReferenceCloth(scene).pos).max(axis=-1) > 1e-9)
    scale = max(1.0, float(np.abs(ref.vel).max()))
    np.testing.assert_allclose(pos, ref.pos, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(vel, ref.vel, rtol=0, atol=1e-7 * scale)
    np.testing.assert_allclose(bp, ref.ball_pos, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(bv, ref.ball_vel, rtol=0, atol=1e-7 * scale)
    np.testing.assert_allclose(cloth.normals(), ref.normals(), rtol=0, atol=1e-7)


@pytest.mark.parametrize("integrator", ["velocity_verlet", "implicit_euler"])
@pytest.mark.parametrize("n", [2, 3, 4, 5, 17])
def test_small_cloths_other_integrators_stay_finite(n: int, integrator: str) -> None:
    """Velocity Verlet and implicit Euler walk the same grid (and implicit Euler one entry
    past it, the ball): on small cloths they must step and stay finite and bounded."""
    effects = [e for e in ALL if e != "wind"] if integrator == "implicit_euler" else ALL
    scene = scene_for(n, effects, "nodes", integrator=integrator)
    for threads in (1, 2):
        cloth = Cloth(scene, backend="cpu", threads=threads)
        cloth.step(FRAMES)
        pos = cloth.positions()
        assert np.all(np.isfinite(pos))
        assert np.abs(pos).max() < 10.0
