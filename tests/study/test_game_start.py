"""The game's start converges in n for every shipped scene with a ball (issue 42).

The start every round has: the flat cloth at rest in the hands, the ball 0.4 m above it.
``game/study/gamestart.py`` samples the ball's and the cloth centre's heights every 50 ms
for 1.5 s through the public ``Cloth`` (CPU float64, one thread); the distance between two
grids is the largest difference of any sample. Each scene is checked against its own finer
grids, nothing hard-coded: the distance between grids whose spacing halves must shrink as
the spacing does (n - 1 = 24, 48, 96, from where issue 42 asks it; slow: n = 97 in float64
is about a minute a scene on a 2-core machine), and where the scene is converged well
enough for play the last distance must be within ``PLAY_MM``. docs/accuracy.md ("The
game's start") has the measured distances and orders of every scene and quantity.
"""

from __future__ import annotations

import functools

import pytest
from clothball.game import Scene
from clothball.game.sim.scene import available
from clothball.game.study.gamestart import StartRun, distance, trajectory
from clothball.game.study.grid import sized

BALL_SCENES = [s for s in available() if "ball" in Scene.load(s).effects]
PLAY_MM = 5.0  # issue 42's target for d(48, 96), the game's n and its double
# The scenes that meet it (docs/accuracy.md, "The game's start": classic and windy, the
# paper's net of tension-only springs without shear or bending, are 7.1 and 6.3 mm off).
WITHIN_PLAY = ("default", "silk")


@functools.cache
def start(name: str, n: int, backend: str = "cpu") -> StartRun:
    return trajectory(sized(Scene.load(name), n), backend=backend, precision="float64",
                      threads=1 if backend == "cpu" else None, sag=False)


def distances(name: str, sizes: tuple[int, ...], record_property,
              backend: str = "cpu") -> list[float]:
    """The trajectories' distances (mm) between successive grids of ``sizes``, recorded."""
    d = [1e3 * distance(start(name, a, backend), start(name, b, backend))
         for a, b in zip(sizes, sizes[1:], strict=False)]
    line = f"{name}: " + ", ".join(f"d({a},{b}) {x:.2f} mm" for a, b, x in zip(
        sizes, sizes[1:], d, strict=False))
    print(line)
    record_property(name, line)
    return d


def test_every_shipped_scene_with_a_ball_is_checked() -> None:
    assert {"default", "classic", "silk", "windy"} <= set(BALL_SCENES)


@pytest.mark.slow
@pytest.mark.parametrize("name", BALL_SCENES)
def test_the_game_start_converges(name: str, record_property) -> None:
    d = distances(name, (25, 49, 97), record_property)
    assert d[1] < d[0], d
    if name in WITHIN_PLAY:
        assert d[1] <= PLAY_MM, d


@pytest.mark.gpu
@pytest.mark.parametrize("name", BALL_SCENES)
def test_the_game_start_converges_on_the_gpu(name: str, cuda: str, record_property) -> None:
    """The larger range on CUDA (float64): the distance keeps shrinking to n = 193."""
    d = distances(name, (25, 49, 97, 193), record_property, backend=cuda)
    assert d[2] < d[1] < d[0], d
