"""A batch's gather of several slots' positions (one transfer: the server's meshes, see
docs/frameloop.md) is each slot's own positions, bit for bit, on both backends."""

from __future__ import annotations

import numpy as np
import pytest
from clothball.game import Scene
from clothball.game.sim.batch import ClothBatch

SCENE = Scene.load("classic").with_changes({"cloth": {"n": 12}})


def test_gathered_positions_are_each_slots_own(backend: str) -> None:
    batch = ClothBatch(SCENE, 5, backend)
    slots = [batch.add() for _ in range(5)]
    for k, s in enumerate(slots):  # each slot pulled its own way
        batch.set_hips(s, batch.hips(s) + np.array([0.01 * k, 0.02 * k, -0.01 * k]))
    batch.remove(slots[1])
    batch.step(20)
    want = [slots[3], slots[0], slots[4]]
    got = batch.gather_positions(want)
    assert got.shape == (3, SCENE.n, SCENE.n, 3)
    for k, s in enumerate(want):
        assert np.array_equal(got[k], batch.positions(s))
    assert not np.array_equal(got[0], got[1])
    assert batch.gather_positions([]).shape == (0, SCENE.n, SCENE.n, 3)
    with pytest.raises(ValueError, match="slot"):
        batch.gather_positions([slots[1]])
