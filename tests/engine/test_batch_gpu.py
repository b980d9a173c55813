"""``ClothBatch`` on CUDA: where the batch steps every slot in one graph a frame (semi-implicit
Euler without strain limiting) and where it falls back to a graph per slot (strain
limiting, velocity Verlet), each slot equals its cloth stepped alone with ``Cloth``
within the oracle tolerance, through odd substep counts (each slot's current buffer flips
every frame), slots paused, resumed, added and removed between steps, gusty wind (new
inputs every frame) and a scene without the ball."""

from __future__ import annotations

import numpy as np
import pytest
from clothball.game import Cloth, ClothBatch, Scene
from clothball.game.sim.stability import auto_substeps

from tests.engine.test_batch import EFFECTS, assert_same, slot_inputs
from tests.engine.test_engine_vs_oracle import scene_with

pytestmark = pytest.mark.gpu

BALL = {"position": [0.0, 1.085, 0.0], "velocity": [0.0, -0.3, 0.0]}


def odd_substeps(scene: Scene) -> int:
    """At least four times the automatic count (a smooth run), made odd."""
    return 4 * auto_substeps(scene) + 1


def case_scene(case: str) -> Scene:
    if case == "ball":  # the batched graph, with the ball's deferred update
        base = scene_with(EFFECTS, ball=BALL)
    elif case == "gusts":  # the batched graph, no ball (its state carried), wind each frame
        base = scene_with(["structural", "shear", "gravity", "damping", "coupling", "wind"],
                          wind={"velocity": [2.0, 0.0, 1.0], "gust_amplitude": 0.5,
                                "gust_period": 0.02})
    elif case == "strain_limit":  # a graph per slot
        base = scene_with(["structural", "gravity", "coupling", "ball", "strain_limit"],
                          ball=BALL, strain_limit={"max_strain": 0.002, "iterations": 4})
    else:  # velocity Verlet: a graph per slot
        base = scene_with(EFFECTS, ball=BALL, sim={"integrator": "velocity_verlet"})
    return base.with_changes({"sim": {"substeps": odd_substeps(base)}})


def prepare(target: ClothBatch | Cloth, k: int, scene: Scene, rest_hips: np.ndarray) -> None:
    """Slot k's hands (and ball): different for every slot."""
    hips, bp, bv = slot_inputs(k, rest_hips)
    if isinstance(target, ClothBatch):
        target.set_hips(k, hips)
        if "ball" in scene.effects:
            target.set_ball(k, bp, bv)
    else:
        target.set_hips(hips)
        if "ball" in scene.effects:
            target.set_ball(bp, bv)


def alone(scene: Scene, precision: str, k: int, frames: int) -> Cloth:
    cloth = Cloth(scene, backend="cuda", precision=precision)
    prepare(cloth, k, scene, cloth.hips())
    cloth.step(frames)
    return cloth


@pytest.mark.parametrize("case", ["ball", "gusts", "strain_limit", "velocity_verlet"])
def test_slots_through_pauses_and_odd_substeps_are_their_cloths_alone(
        case: str, cuda: str, precision: str) -> None:
    scene = case_scene(case)
    assert scene["sim"]["substeps"] % 2 == 1
    batch = ClothBatch(scene, capacity=4, backend=cuda, precision=precision)
    a, b, c = batch.add(), batch.add(), batch.add()
    for k in (a, b, c):
        prepare(batch, k, scene, batch.hips(k))
    batch.step(3)                     # every current buffer flips: 3 x odd substeps
    batch.set_active(b, False)
    batch.step(4)                     # a and c only
    batch.remove(c)
    d = batch.add()                   # c's slot again, at the scene's start
    assert d == c
    prepare(batch, d, scene, batch.hips(d))
    batch.step(5)                     # a and d
    batch.set_active(b, True)         # b rejoins with its buffer a parity behind a's
    assert batch.step(6) == []
    assert (batch.frame(a), batch.frame(b), batch.frame(d)) == (18, 9, 11)
    for k, frames in ((a, 18), (b, 9), (d, 11)):
        assert_same(batch, k, alone(scene, precision, k, frames), exact=False)


@pytest.mark.parametrize("group", [None, "7"])
def test_a_large_batch_steps_each_slot_as_alone(cuda: str, group: str | None,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Many slots in one launch (blocks of different slots side by side), or in groups of 7
    that each go through the frame's substeps in turn (as slots too many for the L2 do):
    the first, a middle and the last slot each equal their cloth alone."""
    if group is not None:
        monkeypatch.setenv("CLOTHBALL_CUDA_BATCH_GROUP", group)
    scene = case_scene("ball")
    batch = ClothBatch(scene, capacity=300, backend=cuda, precision="float32")
    for _ in range(300):
        k = batch.add()
        prepare(batch, k, scene, batch.hips(k))
    assert batch.step(7) == []
    pos, vel, balls = batch.corners_all()
    for k in (0, 151, 299):
        assert_same(batch, k, alone(scene, "float32", k, 7), exact=False)
        p, v = batch.corners(k)
        np.testing.assert_array_equal(pos[k], p)
        np.testing.assert_array_equal(balls[k], np.concatenate(batch.ball(k)))
