"""The pinned Python API: shapes, defaults, layout, validation and the GIL."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from clothball.game import Cloth, Scene
from clothball.game.sim.cloth import corners_of


def small(n: int = 10, **sim) -> Scene:
    return Scene.from_dict({"cloth": {"n": n}, "sim": sim} if sim else {"cloth": {"n": n}})


def test_rest_layout_and_defaults(backend: str) -> None:
    scene = small(7)
    cloth = Cloth(scene, backend=backend, precision="float64")
    assert cloth.backend == backend and cloth.precision == "float64"
    pos = cloth.positions()
    assert pos.shape == (7, 7, 3)
    L = 1.0 / 6
    i, j = 2, 5
    np.testing.assert_allclose(pos[i, j], [-0.5 + j * L, 1.0, -0.5 + i * L])
    np.testing.assert_array_equal(cloth.velocities(), 0.0)
    # Default hand positions: each corner's rest position, so no coupling force at rest.
    np.testing.assert_allclose(cloth.hips(), corners_of(pos))
    np.testing.assert_allclose(cloth.corner_forces(), 0.0)
    assert cloth.substeps >= 1 and cloth.dt == pytest.approx(0.001 / cloth.substeps)


def test_precision_defaults_to_scene(backend: str) -> None:
    assert Cloth(small(), backend=backend).precision == "float32"
    scene = Scene.from_dict({"cloth": {"n": 5}, "sim": {"precision": "float64"}})
    assert Cloth(scene, backend=backend).precision == "float64"


def test_corner_forces_follow_eq7(backend: str) -> None:
    cloth = Cloth(small(), backend=backend, precision="float64")
    rest = cloth.hips()
    h = rest + np.array([[0.1, 0, 0], [0, 0.2, 0], [0, 0, -0.1], [0.05, 0.05, 0.05]])
    cloth.set_hips(h)
    cloth.step(3)
    c, _ = cloth.corners()
    np.testing.assert_allclose(cloth.corner_forces(), -1000.0 * (h - c))
    # Each corner was pulled towards its hand.
    assert np.all(np.linalg.norm(h - c, axis=1) < np.linalg.norm(h - rest, axis=1))
    np.testing.assert_allclose(c, corners_of(cloth.positions()))


def test_ball_setter_and_getter(backend: str) -> None:
    cloth = Cloth(small(), backend=backend, precision="float64")
    cloth.set_ball([0.1, 2.0, -0.1], [0.0, -1.0, 0.5])
    p, v = cloth.ball()
    np.testing.assert_allclose(p, [0.1, 2.0, -0.1])
    np.testing.assert_allclose(v, [0.0, -1.0, 0.5])


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda c: c.set_hips(np.zeros((3, 3))), "h: expected shape"),
        (lambda c: c.set_hips([[np.nan, 0, 0]] + [[0, 0, 0]] * 3), "h: must be finite"),
        (lambda c: c.set_hips([[np.inf, 0, 0]] + [[0, 0, 0]] * 3), "h: must be finite"),
        (lambda c: c.set_hips("abc"), "h: expected"),
        (lambda c: c.step(0), "frames"),
        (lambda c: c.step(1.5), "frames"),
        (lambda c: c.step(True), "frames"),
        (lambda c: c.set_ball([0, 0, np.nan]), "position: must be finite"),
        (lambda c: c.set_ball([0, 0, 0], [0, 0]), "velocity: expected shape"),
        (lambda c: c.set_state(np.zeros((10, 10, 3)), np.zeros((9, 10, 3))), "velocities"),
        (lambda c: c.set_state(np.full((10, 10, 3), np.nan), np.zeros((10, 10, 3))), "positions"),
    ],
)
def test_bad_arguments_raise_and_change_nothing(backend: str, call, match: str) -> None:
    cloth = Cloth(small(), backend=backend, precision="float64")
    cloth.step(2)
    before = (cloth.positions(), cloth.velocities(), cloth.hips(), *cloth.ball(), cloth.frame)
    with pytest.raises(ValueError, match=match):
        call(cloth)
    after = (cloth.positions(), cloth.velocities(), cloth.hips(), *cloth.ball(), cloth.frame)
    for a, b in zip(before, after, strict=True):
        np.testing.assert_array_equal(a, b)


def test_constructor_validation() -> None:
    scene = small()
    with pytest.raises(ValueError, match="backend"):
        Cloth(scene, backend="tpu")
    with pytest.raises(ValueError, match="precision"):
        Cloth(scene, precision="float16")
    with pytest.raises(ValueError, match="scene"):
        Cloth({"cloth": {"n": 4}})  # type: ignore[arg-type]


def test_auto_backend_says_which() -> None:
    cloth = Cloth(small(), backend="auto")
    assert cloth.backend in ("cpu", "cuda")
    assert cloth.backend_note


def test_cuda_without_gpu_is_a_clear_error() -> None:
    from clothball.game import cuda_unavailable_reason

    why = cuda_unavailable_reason()
    if not why:
        pytest.skip("a CUDA device is present")
    with pytest.raises(ValueError, match="'cuda' requested"):
        Cloth(small(), backend="cuda")


def test_step_releases_the_gil() -> None:
    """Another Python thread keeps running while a long step is in native code."""
    cloth = Cloth(small(120, substeps=30), backend="cpu")  # inside the stability bound
    ticks = 0
    done = threading.Event()

    def count() -> None:
        nonlocal ticks
        while not done.is_set():
            ticks += 1
            time.sleep(0.001)

    t = threading.Thread(target=count)
    t.start()
    t0 = time.perf_counter()
    frames = 0
    while time.perf_counter() - t0 < 0.3:
        cloth.step(50)
        frames += 50
    done.set()
    t.join()
    # With the GIL held throughout, the counter could only tick between step() calls.
    assert ticks > frames / 50 + 10


def test_long_requests_go_to_the_engine_in_chunks_that_fit_its_counter(monkeypatch) -> None:
    """The engines count a call's substeps in a 32-bit int; `Cloth.step` splits a request
    so that no call exceeds it (here a cap of 20 substeps stands in for 2**31 - 1) and the
    result is the same as stepping frame by frame."""
    import clothball.game.sim.cloth as cloth_mod

    # 10 substeps: inside the stability bound (masses by area), and 2 frames a chunk of 20.
    scene = Scene.load("classic").with_changes({"cloth": {"n": 8}, "sim": {"substeps": 10}})
    chunked, single = Cloth(scene, backend="cpu"), Cloth(scene, backend="cpu")
    calls: list[tuple[int, int]] = []
    engine = chunked._engine

    class Recording:
        def __getattr__(self, name: str):
            return getattr(engine, name)

        def step(self, frames: int, substeps: int, dt: float) -> None:
            calls.append((frames, substeps))
            engine.step(frames, substeps, dt)

    chunked._engine = Recording()
    monkeypatch.setattr(cloth_mod, "MAX_SUBSTEPS_PER_CALL", 20)
    chunked.step(5)
    for _ in range(5):
        single.step(1)
    assert [f for f, _ in calls] == [2, 2, 1]
    assert all(f * s <= 20 for f, s in calls)
    assert chunked.frame == 5
    np.testing.assert_array_equal(chunked.positions(), single.positions())
