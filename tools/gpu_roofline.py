"""The engine's hot kernels against their roofline (issue 41), on a CUDA machine.

Each case steps many frames in one call (one synchronisation at the end: the GPU's own
rate, launch gaps hidden by the graphs) and reports microseconds a substep, achieved
GFLOP/s and shared-memory GB/s from the counts of game/study/roofline.py, and the
fraction of the bound (the slowest resource at peak). The ball is brought onto the cloth
first (300 frames from its start), so contact is on as in a game. Also:
* the tiled frame's floor a substep (grid barrier, halo exchange, the ball's update):
  a tiny cloth on the tiled path (CLOTHBALL_CUDA_TILED=1, a few nodes a tile) timed at
  two substep counts (16, 80), the difference over the substeps between;
* the plate bending term: the default scene with and without its bending stiffness.
Usage: python3 tools/gpu_roofline.py [--json FILE] [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
import time
from typing import Any

from clothball import _native  # type: ignore[attr-defined]
from clothball.game.sim.batch import ClothBatch
from clothball.game.sim.cloth import Cloth
from clothball.game.sim.scene import Scene
from clothball.game.study import roofline as rl
from clothball.game.study.rooms import room_scene


def timed(step, substeps: int, min_s: float = 0.05, repeats: int = 5) -> float:
    """Median microseconds a substep of `step(frames)` over `repeats` runs of >= min_s."""
    frames = 1
    while True:
        t0 = time.perf_counter()
        step(frames)
        if time.perf_counter() - t0 >= min_s or frames >= 1 << 14:
            break
        frames *= 2
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        step(frames)
        samples.append((time.perf_counter() - t0) / (frames * substeps) * 1e6)
    return statistics.median(samples)


def with_tiled(value: str | None) -> None:
    if value is None:
        os.environ.pop("CLOTHBALL_CUDA_TILED", None)
    else:
        os.environ["CLOTHBALL_CUDA_TILED"] = value


def lone(scene: Scene, precision: str, tiled: str | None) -> tuple[float, str, int]:
    with_tiled(tiled)
    cloth = Cloth(scene, backend="cuda", precision=precision)
    cloth.step(300)  # the ball onto the cloth
    us = timed(cloth.step, cloth.substeps)
    path, substeps = cloth.engine_path, cloth.substeps
    with_tiled(None)
    return us, path, substeps


def rooms(scene: Scene, precision: str, slots: int) -> tuple[float, int]:
    batch = ClothBatch(scene, capacity=slots, backend="cuda", precision=precision)
    for _ in range(slots):
        batch.add()
    batch.step(300)
    return timed(batch.step, batch.substeps), batch.substeps


def row(what: str, scene: Scene, precision: str, path: str, n: int, substeps: int,
        us_substep: float, peaks: rl.Peaks, slots: int = 1) -> dict[str, Any]:
    kernel = "batch_fused" if path == "batch" else path
    nodes = n * n
    # The roofline of the substeps alone (the frame's one pass in and out left out: a
    # substep's share of it is small, and it is the copy's, not the kernel's).
    roof = rl.roofline(scene, precision, kernel, nodes, 1, us_substep, peaks, slots=slots,
                      frame_io=False)
    cost = rl.scene_cost(scene, precision, kernel)
    node_substeps_s = nodes * slots / (us_substep * 1e-6)
    return {"case": what, "scene": scene.name, "precision": precision, "path": path, "n": n,
            "slots": slots, "substeps": substeps, "us_substep": us_substep,
            "ns_node_substep_sm": us_substep * 1e3 * peaks.sms / (nodes * slots),
            "achieved_gflops": cost.flops * node_substeps_s / 1e9,
            "achieved_shared_gbs": cost.shared_bytes * node_substeps_s / 1e9,
            "achieved_dram_gbs": cost.dram_bytes * node_substeps_s / 1e9, **roof}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    copy = _native.cuda_copy_bandwidth_gbs(1 << 30)
    peaks = dataclasses.replace(rl.HOPPER_SXM, copy_gbs=copy)
    classic, default = Scene.load("classic"), Scene.load("default")
    flat = default.with_changes({"cloth": {"bending_stiffness": 0.0}})
    rows: list[dict[str, Any]] = []

    def add(what: str, base: Scene, precision: str, n: int, tiled: str | None) -> None:
        sc = room_scene(base, n)
        us, path, substeps = lone(sc, precision, tiled)
        rows.append(row(what, sc, precision, path, n, substeps, us, peaks))
        print(f"  {what}: {us:.2f} us a substep ({path})", file=sys.stderr, flush=True)

    add("lone substep", classic, "float32", 256, "0")
    add("lone substep", default, "float32", 256, "0")
    for n in ([768] if args.quick else [512, 768, 1024]):
        add("tiled frame", classic, "float32", n, "1")
    add("tiled frame", classic, "float64", 512, "1")
    for n in ([512] if args.quick else [512, 768]):
        add("tiled frame", default, "float32", n, "1")
        add("tiled, no plate", flat, "float32", n, "1")
    for base, n, slots in ((classic, 60, 1024), (default, 48, 1024)):
        sc = room_scene(base, n)
        us, substeps = rooms(sc, "float32", slots)
        rows.append(row("rooms (batched)", sc, "float32", "batch", n, substeps, us, peaks,
                        slots))
        print(f"  rooms {base.name} n={n} x{slots}: {us:.2f} us a substep", file=sys.stderr)

    # The tiled frame's floor a substep: a 64 x 64 cloth cut into ~132 tiles of ~30 nodes.
    floor: dict[int, tuple[float, str]] = {}
    for substeps in (16, 80):
        sc = classic.with_changes({"cloth": {"n": 64}, "sim": {"substeps": substeps}})
        with_tiled("1")
        try:
            cloth = Cloth(sc, backend="cuda", precision="float32")
            cloth.step(300)
            floor[substeps] = (timed(cloth.step, 1), cloth.engine_path)  # us a frame
        except Exception as e:  # noqa: BLE001 - report and still print the rows
            print(f"floor at {substeps} substeps: {e}", file=sys.stderr)
        with_tiled(None)
    barrier_us = ((floor[80][0] - floor[16][0]) / (80 - 16) if len(floor) == 2
                  else float("nan"))

    print(f"device-to-device copy {copy:.0f} GB/s; peaks: {peaks.name}: FP32 "
          f"{peaks.fp32_flops / 1e12:.1f} TFLOP/s, FP64 {peaks.fp64_flops / 1e12:.1f}, "
          f"SFU {peaks.sfu_ops / 1e12:.2f} Tops/s, shared {peaks.shared_bytes / 1e12:.1f} TB/s")
    print(f"{'case':16} {'scene':8} {'prec':7} {'n':>5} {'slots':>5} {'us/sub':>7} "
          f"{'ns/node/SM':>10} {'flop/node':>9} {'sfu':>4} {'smemB':>5} {'GFLOP/s':>8} "
          f"{'smem GB/s':>9} {'bound':>6} {'bound us':>8} {'roofline':>8}")
    for r in rows:
        print(f"{r['case']:16} {r['scene']:8} {r['precision']:7} {r['n']:5d} {r['slots']:5d} "
              f"{r['us_substep']:7.2f} {r['ns_node_substep_sm']:10.2f} "
              f"{r['flops_per_node_substep']:9d} {r['sfu_per_node_substep']:4d} "
              f"{r['shared_bytes_per_node_substep']:5d} {r['achieved_gflops']:8.0f} "
              f"{r['achieved_shared_gbs']:9.0f} {r['bound']:>6} "
              f"{r['bound_us'][r['bound']]:8.3f} {r['roofline_fraction']:8.1%}")
    if len(floor) == 2:
        print(f"tiled frame's floor a substep (barrier, halo, ball; n = 64, {floor[16][1]}): "
              f"{barrier_us:.2f} us (frames of 16 and 80 substeps: {floor[16][0]:.1f}, "
              f"{floor[80][0]:.1f} us)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"rows": rows, "copy_gbs": copy, "barrier_us": barrier_us,
                       "floor_frames_us": {k: v[0] for k, v in floor.items()},
                       "argv": sys.argv[1:]}, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
