"""The roofline's counts (game.study.roofline): how they compose, not the device's rates."""

from __future__ import annotations

import pytest
from clothball.game.sim.scene import Scene
from clothball.game.study import roofline as rl


def test_each_spring_family_adds_four_springs_a_node() -> None:
    base = rl.node_cost({"structural"}, "float32", "tiled")
    more = rl.node_cost({"structural", "shear", "bend"}, "float32", "tiled")
    assert more.flops - base.flops == 8 * rl.SPRING_FLOPS
    assert more.sfu - base.sfu == 8 * rl.SPRING_SFU
    # Eight more neighbour positions read from shared memory, 12 bytes each in float32.
    assert more.shared_bytes - base.shared_bytes == 8 * 12


def test_the_default_scene_costs_its_plate_and_springs() -> None:
    classic = rl.scene_cost(Scene.load("classic"), "float32", "tiled")
    default = rl.scene_cost(Scene.load("default"), "float32", "tiled")
    assert default.flops - classic.flops == 8 * rl.SPRING_FLOPS + rl.PLATE_FLOPS


def test_float64_doubles_the_bytes_and_only_paths_through_memory_move_dram() -> None:
    f32 = rl.node_cost({"structural", "ball"}, "float32", "substeps")
    f64 = rl.node_cost({"structural", "ball"}, "float64", "substeps")
    assert f64.dram_bytes == 2 * f32.dram_bytes == 2 * 4 * 12
    assert rl.node_cost({"structural"}, "float32", "tiled").dram_bytes == 0
    assert rl.node_cost({"structural"}, "float32", "substeps").shared_bytes == 0


def test_the_bound_is_the_slowest_resource_and_scales_with_the_work() -> None:
    scene = Scene.load("classic")
    one = rl.roofline(scene, "float32", "tiled", 768 * 768, 40, 1000.0)
    two = rl.roofline(scene, "float32", "tiled", 768 * 768, 80, 1000.0)
    assert one["bound_us"][one["bound"]] == max(one["bound_us"].values())
    assert two["roofline_fraction"] == pytest.approx(2 * one["roofline_fraction"], rel=1e-2)
    # At peak every FP32 lane does an FMA a clock: 132 x 128 x 2 x 1.98 GHz.
    assert rl.HOPPER_SXM.fp32_flops == pytest.approx(66.9e12, rel=1e-3)


def test_where_nsight_counted_the_instructions_issue_is_the_bound() -> None:
    # The tiled frame, classic n = 768, 100 substeps: Nsight Compute saw its issue slots
    # 70 % busy over 862.6 us, so 604 us of issue at 100 %: what the count gives back.
    roof = rl.roofline(Scene.load("classic"), "float32", "tiled", 768 * 768, 100, 862.6)
    assert roof["bound"] == "issue"
    assert roof["bound_us"]["issue"] == pytest.approx(0.7005 * 862.6, rel=5e-3)
    assert roof["roofline_fraction"] == pytest.approx(0.7005, rel=5e-3)
    # No count for the launch-a-substep path: the bound is then one of the counted
    # resources.
    lone = rl.roofline(Scene.load("classic"), "float64", "substeps", 256 * 256, 43, 300.0)
    assert "issue" not in lone["bound_us"] and lone["instructions_per_node_substep"] is None
    # Float64's count (Nsight Compute, classic n = 640, 68 substeps: 386.8 M warp
    # instructions), as the record has it.
    f64 = rl.roofline(Scene.load("classic"), "float64", "tiled", 640 * 640, 68, 815.2)
    assert f64["instructions_per_node_substep"] == pytest.approx(
        386_785_308 * 32 / (640 * 640 * 68), rel=1e-3)


def test_the_tiled_frame_adds_its_barriers_floor() -> None:
    """The tiled frame's bound is its barriers' measured floor a substep plus its nodes'
    time at peak: with the floor at 3.44 us, 100 substeps add 344 us, whatever the size;
    the paths without a grid barrier have none."""
    scene = Scene.load("classic")
    roof = rl.roofline(scene, "float32", "tiled", 768 * 768, 100, 1000.0)
    assert roof["barrier_us"] == pytest.approx(100 * rl.HOPPER_SXM.barrier_us)
    assert roof["roofline_fraction_with_barrier"] == pytest.approx(
        roof["roofline_fraction"] + 0.344, rel=1e-9)
    alone = rl.roofline(scene, "float32", "substeps", 256 * 256, 100, 1000.0)
    assert alone["barrier_us"] == 0.0 and alone["roofline_fraction_with_barrier"] == 0.0
    bare = rl.Peaks("no floor", 132, 1.98)
    assert rl.roofline(scene, "float32", "tiled", 768 * 768, 100, 1000.0,
                       bare)["barrier_us"] == 0.0
