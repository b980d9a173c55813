"""``ClothBatch``: each slot against the NumPy float64 oracle with its own hands and ball,
each slot equal to the same cloth stepped alone with ``Cloth`` (bit for bit on the CPU),
slots added and removed without touching the others, a failing slot reset alone."""

from __future__ import annotations

import numpy as np
import pytest
from clothball.game import Cloth, ClothBatch, ReferenceCloth, Scene
from clothball.game.sim.stability import (
    auto_substeps,
    auto_substeps_all,
    substep_speed_limits,
    substeps_for_speeds,
)

from tests.engine.test_engine_vs_oracle import FRAMES, allowed_drift, scene_with

EFFECTS = ["structural", "shear", "gravity", "damping", "ball", "coupling"]


def batch_scene() -> Scene:
    """Fixed substeps (four times the automatic count at rest: a smooth run, where rounding
    errors are not amplified), so slots with different balls share the count a lone cloth
    of theirs would take."""
    ball = {"position": [0.0, 1.085, 0.0], "velocity": [0.0, -0.3, 0.0]}
    return scene_with(EFFECTS, ball=ball,
                      sim={"substeps": 4 * auto_substeps(scene_with(EFFECTS, ball=ball))})


def slot_inputs(k: int, rest_hips: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hands, ball position and velocity of slot k: different for every slot."""
    rng = np.random.default_rng(100 + k)
    hips = rest_hips + rng.uniform(-0.006, 0.006, size=(4, 3))
    ball_p = np.array([0.002 * (k - 1), 1.085 + 0.002 * k, -0.001 * k])
    ball_v = np.array([0.0, -0.3 - 0.02 * k, 0.01 * k])
    return hips, ball_p, ball_v


def state(pos, vel, bp, bv) -> np.ndarray:
    return np.concatenate([np.ravel(pos), np.ravel(vel), bp, bv])


def test_each_slot_matches_the_oracle(backend: str, precision: str) -> None:
    scene = batch_scene()
    batch = ClothBatch(scene, capacity=4, backend=backend, precision=precision)
    slots = [batch.add() for _ in range(3)]
    assert slots == [0, 1, 2]
    refs = []
    for k in slots:
        ref = ReferenceCloth(scene)
        hips, bp, bv = slot_inputs(k, ref.hips)
        batch.set_hips(k, hips)
        batch.set_ball(k, bp, bv)
        ref.hips, ref.ball_pos, ref.ball_vel = hips, bp.copy(), bv.copy()
        refs.append(ref)
    assert batch.step(FRAMES) == []
    for k, ref in zip(slots, refs, strict=True):
        ref.step(FRAMES, batch.substeps)

        def make(s: Scene, k: int = k) -> ReferenceCloth:
            r = ReferenceCloth(s)
            hips, bp, bv = slot_inputs(k, r.hips)
            r.ball_pos, r.ball_vel = bp.copy(), bv.copy()
            return r

        tol = allowed_drift(scene, precision, batch.substeps, ref.hips, make=make)
        got = state(batch.positions(k), batch.velocities(k), *batch.ball(k))
        want = state(ref.pos, ref.vel, ref.ball_pos, ref.ball_vel)
        err = np.abs(got - want).max()
        assert err <= tol, f"slot {k}: max error {err:.3g} > allowed {tol:.3g}"
        assert np.abs(want - state(*_start(scene))).max() > 100 * tol  # it moved
        np.testing.assert_allclose(batch.corner_forces(k), ref.corner_forces(), rtol=0,
                                   atol=2000 * tol)


def _start(scene: Scene) -> tuple[np.ndarray, ...]:
    r = ReferenceCloth(scene)
    return r.pos, r.vel, r.ball_pos, r.ball_vel


def alone(scene: Scene, backend: str, precision: str, k: int, frames: int) -> Cloth:
    cloth = Cloth(scene, backend=backend, precision=precision, threads=1)
    hips, bp, bv = slot_inputs(k, cloth.hips())
    cloth.set_hips(hips)
    cloth.set_ball(bp, bv)
    cloth.step(frames)
    return cloth


def assert_same(batch: ClothBatch, slot: int, cloth: Cloth, exact: bool) -> None:
    got = state(batch.positions(slot), batch.velocities(slot), *batch.ball(slot))
    want = state(cloth.positions(), cloth.velocities(), *cloth.ball())
    if exact:
        assert np.array_equal(got, want), f"slot {slot}: {np.abs(got - want).max():.3g}"
    else:  # within the oracle tolerance of the one-cloth engine
        tol = allowed_drift(batch.scene, batch.precision, batch.substeps, cloth.hips())
        assert np.abs(got - want).max() <= tol
    c_pos, c_vel = batch.corners(slot)
    w_pos, w_vel = cloth.corners()
    np.testing.assert_allclose(c_pos, w_pos, rtol=0, atol=0 if exact else 1e-5)
    np.testing.assert_allclose(c_vel, w_vel, rtol=0, atol=0 if exact else 1e-4)


def test_each_slot_is_that_cloth_stepped_alone(backend: str, precision: str) -> None:
    scene = batch_scene()
    batch = ClothBatch(scene, capacity=5, backend=backend, precision=precision)
    for k in range(5):
        assert batch.add() == k
        hips, bp, bv = slot_inputs(k, batch.hips(k))
        batch.set_hips(k, hips)
        batch.set_ball(k, bp, bv)
    batch.step(30)
    for k in range(5):
        assert_same(batch, k, alone(scene, backend, precision, k, 30), backend == "cpu")


def test_all_slot_arrays_in_and_out(backend: str) -> None:
    """set_hips_all / corners_all carry the same values as the per-slot calls."""
    scene = batch_scene()
    batch = ClothBatch(scene, capacity=3, backend=backend, precision="float64")
    for _ in range(3):
        batch.add()
    hips = np.stack([slot_inputs(k, batch.hips(k))[0] for k in range(3)])
    batch.set_hips_all(hips)
    for k in range(3):
        np.testing.assert_array_equal(batch.hips(k), hips[k])
    batch.step(10)
    pos, vel, balls = batch.corners_all()
    assert pos.shape == vel.shape == (3, 4, 3) and balls.shape == (3, 6)
    for k in range(3):
        p, v = batch.corners(k)
        bp, bv = batch.ball(k)
        np.testing.assert_array_equal(pos[k], p)
        np.testing.assert_array_equal(vel[k], v)
        np.testing.assert_array_equal(balls[k], np.concatenate([bp, bv]))
    with pytest.raises(ValueError, match="h: expected shape"):
        batch.set_hips_all(np.zeros((2, 4, 3)))
    with pytest.raises(ValueError, match="h: "):
        batch.set_hips_all(np.full((3, 4, 3), np.nan))


def test_adding_and_removing_slots_leaves_the_others_alone(backend: str) -> None:
    scene = batch_scene()
    batch = ClothBatch(scene, capacity=4, backend=backend, precision="float32")
    a, b = batch.add(), batch.add()
    for k in (a, b):
        hips, bp, bv = slot_inputs(k, batch.hips(k))
        batch.set_hips(k, hips)
        batch.set_ball(k, bp, bv)
    batch.step(10)
    batch.remove(b)
    c = batch.add()  # takes b's freed slot, at the scene's start
    assert c == b and batch.frame(c) == 0 and batch.slots() == [a, c]
    start = Cloth(scene, backend=backend, precision="float32")
    np.testing.assert_array_equal(batch.positions(c), start.positions())
    d = batch.add()
    assert batch.frame(d) == 0
    batch.step(20)
    assert batch.frame(a) == 30 and batch.frame(c) == batch.frame(d) == 20
    assert_same(batch, a, alone(scene, backend, "float32", a, 30), backend == "cpu")
    assert batch.slots() == [a, c, d]
    with pytest.raises(ValueError, match="not an occupied slot"):
        batch.positions(3)


def test_a_paused_slot_keeps_its_state_and_resumes_as_if_never_paused(backend: str) -> None:
    scene = batch_scene()
    batch = ClothBatch(scene, capacity=3, backend=backend, precision="float32")
    a, b = batch.add(), batch.add()
    for k in (a, b):
        hips, bp, bv = slot_inputs(k, batch.hips(k))
        batch.set_hips(k, hips)
        batch.set_ball(k, bp, bv)
    batch.step(10)
    batch.set_active(b, False)
    held = batch.positions(b), batch.velocities(b), batch.ball(b)
    batch.step(15)  # a steps, b does not
    assert not batch.active(b) and batch.frame(a) == 25 and batch.frame(b) == 10
    np.testing.assert_array_equal(batch.positions(b), held[0])
    np.testing.assert_array_equal(batch.velocities(b), held[1])
    np.testing.assert_array_equal(batch.ball(b)[0], held[2][0])
    batch.set_active(b, True)
    batch.step(5)
    # Each slot is its cloth stepped alone for the frames it was active.
    assert_same(batch, a, alone(scene, backend, "float32", a, 30), backend == "cpu")
    assert_same(batch, b, alone(scene, backend, "float32", b, 15), backend == "cpu")
    batch.set_active(a, False)
    batch.set_active(b, False)
    assert batch.step(7) == [] and (batch.frame(a), batch.frame(b)) == (30, 15)


def test_a_failing_slot_is_reset_alone_and_the_others_step_on(backend: str) -> None:
    scene = batch_scene()
    batch = ClothBatch(scene, capacity=3, backend=backend, precision="float32")
    for k in range(3):
        batch.add()
        hips, bp, bv = slot_inputs(k, batch.hips(k))
        batch.set_hips(k, hips)
        batch.set_ball(k, bp, bv)
    batch.step(5)
    # Slot 1 explodes: velocities far beyond float32's range after a few substeps.
    pos = batch.positions(1)
    batch.set_state(1, pos, np.full_like(pos, 3e37))
    failed = batch.step(5)
    assert failed == [1] and batch.failures == 1
    assert batch.frame(1) == 0  # reset to the scene's start
    start = Cloth(scene, backend=backend, precision="float32")
    np.testing.assert_array_equal(batch.positions(1), start.positions())
    assert batch.frame(0) == batch.frame(2) == 10
    for k in (0, 2):
        assert_same(batch, k, alone(scene, backend, "float32", k, 10), backend == "cpu")
    removing = ClothBatch(scene, capacity=2, backend=backend, on_failure="remove")
    s0, s1 = removing.add(), removing.add()
    p = removing.positions(s1)
    removing.set_state(s1, p, np.full_like(p, 1e308))
    assert removing.step(3) == [s1] and removing.slots() == [s0]


def test_automatic_substeps_are_the_largest_any_slot_needs() -> None:
    base = scene_with(EFFECTS, ball={"position": [0.0, 1.085, 0.0], "velocity": [0.0, 0.0, 0.0]})
    batch = ClothBatch(base, capacity=3, backend="cpu")
    for _ in range(3):
        batch.add()
    calm = auto_substeps(base, 0.0)
    assert batch.substeps == calm
    # A fast ball needs more (60 m/s: with masses by area the calm count is the 40 m/s one's).
    batch.set_ball(2, [0.0, 1.3, 0.0], [0.0, -60.0, 0.0])
    fast = auto_substeps(base, 60.0)
    assert fast > calm and batch.substeps == fast
    batch.remove(2)
    assert batch.substeps == calm


def test_bad_arguments_are_refused_with_their_name() -> None:
    scene = batch_scene()
    for cap in (0, -1, 1.5, True, 70_000):
        with pytest.raises(ValueError, match="capacity"):
            ClothBatch(scene, capacity=cap, backend="cpu")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="on_failure"):
        ClothBatch(scene, capacity=1, backend="cpu", on_failure="explode")  # type: ignore
    batch = ClothBatch(scene, capacity=1, backend="cpu")
    batch.add()
    with pytest.raises(ValueError, match="all 1 slots are taken"):
        batch.add()
    for bad in (-1, 1, 2.0, "0"):
        with pytest.raises(ValueError, match="slot"):
            batch.set_hips(bad, np.zeros((4, 3)))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="frames"):
        batch.step(0)


@pytest.mark.parametrize("name", ["classic", "default", "windy", "silk"])
def test_the_substep_lookup_is_the_stability_formula(name: str) -> None:
    """What a cloth and a batch ask after each frame (a lookup in the scene's speed table)
    is ``auto_substeps_all`` itself: random speeds, every boundary of the table and the
    floats either side of it, rest, and speeds past the table (the formula's)."""
    scene = Scene.load(name)
    limits = substep_speed_limits(scene)
    edges = limits[limits >= 0]
    speeds = np.concatenate([
        np.random.default_rng(3).uniform(0.0, 2.0 * edges.max(initial=1.0), 20_000),
        edges, np.nextafter(edges, np.inf), np.nextafter(edges, -np.inf),
        [0.0, 1e-9, 1e5, 1e7],
    ])
    speeds = speeds[speeds >= 0]
    assert np.array_equal(substeps_for_speeds(scene, speeds), auto_substeps_all(scene, speeds))
