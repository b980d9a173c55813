"""``clothball bench --largest``: the largest cloth one engine steps at 1 kHz.

A frame here is what a haptic loop does every millisecond: the four hands go in
(``set_hips``), the cloth steps one frame of its scene's automatic substeps, and the corners
come out (``corners``). For each scene and precision, n is bisected for the largest cloth
whose frame p99 stays within the 1 ms a 1 kHz frame has. Beside it: the bytes a design
that passes over the state once a substep must move through device memory per simulated
millisecond, and those of one pass a frame (the CUDA tiled frame's: the state in and out
once, the substeps on chip), each against the device's copy bandwidth.

A single sample of a frame-time p99 is noisy (the size found moved by 30-80 between runs
that quoted one), so each size is timed ``repeats`` times, a fresh cloth each time, and
judged by the median of the repeats' p99s; every row says which path stepped it and the
fraction of the roofline bound (``game.study.roofline``) its median frame reaches.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ..sim.cloth import Cloth
from ..sim.scene import Scene
from . import roofline as rl
from .rooms import FRAME_BUDGET_US, room_scene

# Issue 29's targets (H100): (scene, precision) -> n held at 1 kHz.
TARGETS = {("classic", "float32"): 1024, ("classic", "float64"): 720,
           ("default", "float32"): 768}
START_N = 512   # the bisection's first size
MAX_N = 2048    # and its largest
STEP_N = 8      # sizes tried are multiples of this
GIVE_UP = 3.0   # a size whose warm-up frames take this many budgets is not timed further
REPEATS = 3     # each size timed this many times (a fresh cloth each), the median p99 judged


def frame_times(scene: Scene, backend: str, precision: str, frames: int,
                warmup: int = 30) -> tuple[np.ndarray, str]:
    """Microseconds of each of ``frames`` frames (hands in, one frame, corners out), and
    the engine's path. Fewer frames when the warm-up already takes GIVE_UP budgets."""
    cloth = Cloth(scene, backend=backend, precision=precision)
    rest = cloth.hips()
    out = []
    for f in range(-warmup, frames):
        hips = rest + 0.01 * np.sin(2.0 * np.pi * f / 500.0)  # hands on the move
        t0 = time.perf_counter()
        cloth.set_hips(hips)
        cloth.step(1)
        cloth.corners()
        us = (time.perf_counter() - t0) * 1e6
        if f >= 0:
            out.append(us)
        elif f == -1 and us > GIVE_UP * FRAME_BUDGET_US:
            out.append(us)  # far over budget: one frame says so
            break
    return np.array(out), cloth.engine_path


def traffic(n: int, precision: str, substeps: int, copy_gbs: float | None) -> dict[str, Any]:
    """Device-memory bytes per simulated millisecond (one 1 ms frame): one pass over the
    state (6 planes read, 6 written) a substep, and one a frame."""
    pass_bytes = 12 * (4 if precision == "float32" else 8) * n * n
    out: dict[str, Any] = {"pass_bytes": pass_bytes,
                           "pass_a_substep_gbs": pass_bytes * substeps / 1e-3 / 1e9,
                           "pass_a_frame_gbs": pass_bytes / 1e-3 / 1e9}
    if copy_gbs:
        out["pass_a_substep_of_copy"] = out["pass_a_substep_gbs"] / copy_gbs
        out["pass_a_frame_of_copy"] = out["pass_a_frame_gbs"] / copy_gbs
    return out


def measure(base: Scene, backend: str, precision: str, n: int, frames: int,
            copy_gbs: float | None, repeats: int = 1) -> dict[str, Any]:
    """One size timed ``repeats`` times (a fresh cloth each): held when the median of the
    repeats' frame p99s is within budget (and no repeat gave up)."""
    scene = room_scene(base, n)
    substeps = int(scene["sim"]["substeps"])
    p50s, p99s, complete, path = [], [], True, ""
    for _ in range(repeats):
        times, path = frame_times(scene, backend, precision, frames)
        p50, p99 = np.percentile(times, [50, 99])
        p50s.append(float(p50))
        p99s.append(float(p99))
        complete = complete and times.size == frames
        if not complete:
            break  # far over budget: further repeats say nothing more
    p50, p99 = float(np.median(p50s)), float(np.median(p99s))
    row: dict[str, Any] = {
        "scene": base.name, "backend": backend, "precision": precision, "n": n,
        "substeps": substeps, "path": path, "frames": frames, "repeats": len(p99s),
        "frame_us_p50": p50, "frame_us_p99": p99, "frame_us_p99_repeats": p99s,
        "held": bool(p99 <= FRAME_BUDGET_US and complete),
        **traffic(n, precision, substeps, copy_gbs)}
    if backend == "cuda":
        peaks = dataclasses.replace(rl.HOPPER_SXM, copy_gbs=copy_gbs)
        kernel_path = path if path in ("tiled", "substeps", "node_a_thread") else "substeps"
        row["roofline"] = rl.roofline(scene, precision, kernel_path, n * n, substeps, p50,
                                      peaks)
        row["roofline_fraction"] = row["roofline"]["roofline_fraction"]
        row["bound"] = row["roofline"]["bound"]
        if row["roofline"]["barrier_us"]:
            row["roofline_fraction_with_barrier"] = row["roofline"][
                "roofline_fraction_with_barrier"]
    return row


def largest_held(held: Callable[[int], bool], start: int = START_N, top: int = MAX_N,
                 step: int = STEP_N) -> int:
    """The largest multiple of ``step`` up to ``top`` that ``held`` accepts (0: none),
    assuming a larger cloth is never faster: doubling (or halving) from ``start`` until
    the answer changes, then bisection between the largest held and the smallest not."""
    lo, hi = 0, 0  # largest held so far, smallest not held (0: none yet)
    n = start
    while True:
        if held(n):
            lo = n
            if n >= top or hi:
                break
            n = min(top, 2 * n)
        else:
            hi = n
            if lo or n <= step:
                break
            n = max(step, n // 2 // step * step)
    while hi and hi - lo > step:
        mid = (lo + hi) // 2 // step * step
        if held(mid):
            lo = mid
        else:
            hi = mid
    return lo


def run_largest(cases: list[tuple[Scene, str, str]], frames: int, top: int,
                copy_gbs: float | None, progress: Callable[[str], None],
                repeats: int = 1) -> list[dict[str, Any]]:
    """Every size tried (up to ``top``) for each (scene, backend, precision), in order, each
    timed ``repeats`` times; the largest held is the row with ``largest`` set."""
    rows: list[dict[str, Any]] = []
    for base, backend, precision in cases:
        tried: dict[int, dict[str, Any]] = {}

        def held(n: int, base: Scene = base, backend: str = backend,
                 precision: str = precision, tried: dict[int, dict[str, Any]] = tried) -> bool:
            tried[n] = measure(base, backend, precision, n, frames, copy_gbs, repeats)
            progress(f"{base.name} {precision} n={n} ({tried[n]['path']}): p99 "
                     f"{tried[n]['frame_us_p99']:.0f} us (median of {tried[n]['repeats']})")
            return tried[n]["held"]

        best = largest_held(held, start=min(START_N, top // STEP_N * STEP_N), top=top)
        for n in sorted(tried):
            rows.append({**tried[n], "largest": n == best})
    return rows


def print_largest(rows: list[dict[str, Any]], copy_gbs: float | None) -> None:
    if copy_gbs:
        print(f"device-to-device copy: {copy_gbs:.0f} GB/s (read + write)")
    reps = max((r.get("repeats", 1) for r in rows), default=1)
    print(f"p99: the median of {reps} repeats' p99s (each {rows[0]['frames'] if rows else 0} "
          "frames); roofline: the bound's time over the frame's p50 (game.study.roofline)")
    print(f"{'scene':8} {'precision':9} {'n':>5} {'substeps':>8} {'path':>13} {'p50 us':>8} "
          f"{'p99 us':>8} {'p99 min-max':>13} {'roofline':>9} {'bound':>6}  held")
    for r in rows:
        p99s = r.get("frame_us_p99_repeats", [r["frame_us_p99"]])
        spread = f"{min(p99s):.0f}-{max(p99s):.0f}"
        frac = f"{r['roofline_fraction']:.1%}" if "roofline_fraction" in r else "-"
        print(f"{r['scene']:8} {r['precision']:9} {r['n']:5d} {r['substeps']:8d} "
              f"{r['path']:>13} {r['frame_us_p50']:8.1f} {r['frame_us_p99']:8.1f} "
              f"{spread:>13} {frac:>9} {r.get('bound', '-'):>6}  "
              f"{'yes' if r['held'] else 'no'}")
    print("\nlargest n held at 1 kHz (frame p99 <= 1 ms, corners read each frame):")
    for r in rows:
        if not r["largest"]:
            continue
        target = TARGETS.get((r["scene"], r["precision"]))
        verdict = "" if target is None else (
            f"; target {target}: {'met' if r['n'] >= target else 'MISSED'}")
        of = ""
        if copy_gbs:
            of = (f" ({r['pass_a_substep_of_copy']:.1f}x the copy bandwidth; one pass a "
                  f"frame: {r['pass_a_frame_gbs']:.0f} GB/s, "
                  f"{r['pass_a_frame_of_copy']:.1%})")
        roof = ""
        if "roofline_fraction" in r:
            roof = f"; roofline {r['roofline_fraction']:.1%} of its {r['bound']} bound"
            if "roofline_fraction_with_barrier" in r:
                roof += (f" ({r['roofline_fraction_with_barrier']:.1%} with the grid "
                         f"barrier's floor)")
        print(f"  {r['scene']} {r['precision']} ({r['backend']}): n = {r['n']}, p99 "
              f"{r['frame_us_p99']:.0f} us (median of {r.get('repeats', 1)}), {r['path']}"
              f"{roof}; a pass a substep would move "
              f"{r['pass_a_substep_gbs']:.0f} GB per simulated s{of}{verdict}")
    missing = {(r["scene"], r["precision"], r["backend"]) for r in rows} - {
        (r["scene"], r["precision"], r["backend"]) for r in rows if r["largest"]}
    for scene, precision, backend in sorted(missing):
        print(f"  {scene} {precision} ({backend}): no size held")
