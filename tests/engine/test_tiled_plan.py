"""The CUDA tiled frame's layout and when a cloth takes it (core/tiled_plan.hpp), checked
without a GPU: the plan is plain C++ that the bindings expose."""

from __future__ import annotations

import pytest
from clothball import _native
from clothball.game import Scene
from clothball.game.sim.cloth import native_config

# An H100 SXM: 132 multiprocessors, 227 KB of shared memory a block (opt-in).
H100_SMS, H100_SHARED = 132, 232448


def config(scene: str, n: int, **changes: dict) -> _native.Config:
    return native_config(Scene.load(scene).with_changes({"cloth": {"n": n}, **changes}))


def plan(c: _native.Config, dbl: bool = False, blocks: int = H100_SMS,
         shared: int = H100_SHARED) -> dict | None:
    return _native.tiled_plan(c, dbl, blocks, shared)


@pytest.mark.parametrize("scene", ["classic", "default"])
@pytest.mark.parametrize("dbl", [False, True])
@pytest.mark.parametrize("n", [2, 14, 60, 131, 384, 720, 1024])
def test_tiles_cover_the_cloth_within_the_device(scene: str, dbl: bool, n: int) -> None:
    c = config(scene, n)
    t = plan(c, dbl)
    if t is None:  # does not fit: only large float64 cloths
        assert dbl and n == 1024
        return
    reach = 2 if scene == "default" else 1  # bending springs reach two nodes
    assert t["reach"] == reach
    assert t["tiles_y"] * t["tiles_x"] <= H100_SMS  # a block a multiprocessor, all resident
    for tiles, size in ((t["tiles_y"], t["th"]), (t["tiles_x"], t["tw"])):
        assert (tiles - 1) * size < n <= tiles * size  # every node, and no empty tile
    real = 8 if dbl else 4
    assert t["shared_bytes"] == (t["th"] + 2 * reach) * (t["tw"] + 2 * reach) * 6 * real
    assert t["shared_bytes"] <= H100_SHARED


def test_the_issue_sizes_fit_an_h100() -> None:
    """Issue 29's targets: classic n = 1024 float32 and n = 720 float64, default n = 768
    float32 run tiled, on the whole device, no tile larger than those of the even 12 x 11
    cut of n = 1024 (86 x 94 nodes)."""
    t = plan(config("classic", 1024))
    assert t["tiles_y"] * t["tiles_x"] == 132
    assert t["th"] * t["tw"] <= 86 * 94
    assert plan(config("classic", 720), dbl=True)["chosen"]
    assert plan(config("default", 768))["chosen"]
    assert plan(config("classic", 1024))["chosen"]


def test_no_plan_where_the_state_does_not_fit_on_chip() -> None:
    assert plan(config("classic", 2048)) is None
    assert plan(config("classic", 1024), blocks=66) is None  # half the device
    assert plan(config("classic", 64), shared=1000) is None


CLASSIC = ["structural", "gravity", "damping", "ball", "coupling"]  # what its keys need


@pytest.mark.parametrize("changes", [
    {"sim": {"effects": [*CLASSIC, "wind"]}},
    {"sim": {"effects": [*CLASSIC, "strain_limit"]}},
    {"sim": {"integrator": "velocity_verlet"}},
    {"sim": {"integrator": "implicit_euler"}},
])
def test_configurations_that_cannot_run_tiled(changes: dict) -> None:
    """Wind reads the neighbours' velocities (updated in place in a tile), strain limiting
    runs along whole lines, the other integrators have their own kernels."""
    assert plan(config("classic", 512, **changes)) is None


def test_chosen_from_the_threshold_or_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """From TILED_MIN_N, or TILED_MIN_N_BEND where bending springs reach two nodes (the
    default scene: more to compute a node for the state it keeps on chip)."""
    monkeypatch.delenv("CLOTHBALL_CUDA_TILED", raising=False)
    assert _native.TILED_MIN_N_BEND < _native.TILED_MIN_N
    for scene, least in (("classic", _native.TILED_MIN_N),
                         ("default", _native.TILED_MIN_N_BEND)):
        assert not plan(config(scene, least - 8))["chosen"]
        assert plan(config(scene, least))["chosen"]
    large = _native.TILED_MIN_N
    monkeypatch.setenv("CLOTHBALL_CUDA_TILED", "1")  # wherever it fits
    assert plan(config("classic", 14))["chosen"]
    monkeypatch.setenv("CLOTHBALL_CUDA_TILED", "0")  # never
    assert not plan(config("classic", large))["chosen"]


@pytest.mark.parametrize("n", [512, 640, 688, 704, 768, 832, 1024])
def test_tiles_are_compact_within_the_slack_of_the_fewest_nodes(
    n: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Every tiling the device holds, as tiled_plan enumerates it: its largest tile.
    shapes = []
    for ty in range(1, H100_SMS + 1):
        th = -(-n // ty)
        rows = -(-n // th)
        tx = min(H100_SMS // rows, n)
        if tx >= 1:
            tw = -(-n // tx)
            if (th + 2) * (tw + 2) * 6 * 4 <= H100_SHARED:
                shapes.append((th, tw))
    fewest = min(th * tw for th, tw in shapes)
    near = [(th, tw) for th, tw in shapes if th * tw <= fewest * 1.03]
    t = plan(config("classic", n))
    assert t["th"] + t["tw"] == min(th + tw for th, tw in near)
    assert t["th"] * t["tw"] <= fewest * 1.03
    # CLOTHBALL_CUDA_TILED_PLAN=work takes the fewest nodes alone (the plan before).
    monkeypatch.setenv("CLOTHBALL_CUDA_TILED_PLAN", "work")
    assert plan(config("classic", n))["th"] * plan(config("classic", n))["tw"] == fewest


def test_a_tall_thin_tile_is_not_taken_for_a_few_nodes_less() -> None:
    # n = 688: 4 x 33 tiles of 172 x 21 (3 612 nodes) against 11 x 12 of 63 x 58 (3 654).
    t = plan(config("classic", 688))
    assert (t["tiles_y"], t["tiles_x"], t["th"], t["tw"]) == (11, 12, 63, 58)
