"""``clothball bench --rooms``: how many rooms one engine steps at 1 kHz.

A room here is a slot of a ``ClothBatch``: every frame, each room's four hands go in
(``set_hips_all``), every room steps one frame, and each room's corners and ball come out
(``corners_all``), with no network. Beside it, what a room's MESH costs the engine: every
room's nodes read back in one gather (``gather_positions``, the server's frame loop's
copy), per room. The number of rooms grows (doubling, then bisecting)
until the p99 of that frame time passes the 1 ms a 1 kHz frame has; the largest count that
stays within it is the count held.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from ..sim.batch import ClothBatch
from ..sim.scene import Scene
from ..sim.stability import auto_substeps

FRAME_BUDGET_US = 1000.0  # 1 kHz
# Issue 17's targets: (backend, precision, n) -> rooms held at 1 kHz.
TARGETS = {("cuda", "float32", 60): 1000, ("cpu", "float32", 16): 40,
           ("cpu", "float32", 60): 6}


def room_scene(base: Scene, n: int) -> Scene:
    """``base`` at size n with its automatic substep count at rest, fixed (every slot
    then steps the same count)."""
    sized = base.with_changes({"cloth": {"n": n}})
    return sized.with_changes({"sim": {"substeps": auto_substeps(sized)}})


def frame_times(scene: Scene, rooms: int, backend: str, precision: str, frames: int,
                warmup: int = 30) -> tuple[np.ndarray, float, int | None]:
    """Microseconds of each of ``frames`` frames for ``rooms`` rooms: hands in, one step,
    corners and balls out; the median microseconds per room of reading every room's
    nodes back in one gather (a MESH's copy); and the CPU threads the batch chose."""
    batch = ClothBatch(scene, capacity=rooms, backend=backend, precision=precision)
    for _ in range(rooms):
        batch.add()
    rest = np.stack([batch.hips(s) for s in range(rooms)])
    phase = np.linspace(0.0, 2.0 * np.pi, rooms, endpoint=False)[:, None, None]
    out = np.empty(frames)
    for f in range(-warmup, frames):
        hips = rest + 0.01 * np.sin(2.0 * np.pi * f / 500.0 + phase)  # hands on the move
        t0 = time.perf_counter()
        batch.set_hips_all(hips)
        batch.step(1)
        batch.corners_all()
        if f >= 0:
            out[f] = (time.perf_counter() - t0) * 1e6
    slots = list(range(rooms))
    gathers = np.empty(max(5, frames // 100))
    for k in range(gathers.size):
        t0 = time.perf_counter()
        batch.gather_positions(slots)
        gathers[k] = (time.perf_counter() - t0) * 1e6 / rooms
    return out, float(np.median(gathers)), batch.threads


def row(backend: str, precision: str, n: int, rooms: int, times: np.ndarray,
        substeps: int, mesh_us: float, threads: int | None = None) -> dict[str, Any]:
    p50, p99 = np.percentile(times, [50, 99])
    return {"backend": backend, "precision": precision, "n": n, "rooms": rooms,
            "threads": threads,
            "substeps": substeps, "frames": int(times.size), "frame_us_p50": float(p50),
            "frame_us_p99": float(p99), "mesh_us_per_room": mesh_us,
            "held": bool(p99 <= FRAME_BUDGET_US)}


def counts(max_rooms: int, held: Callable[[int], bool]) -> Iterator[int]:
    """Room counts to try: 1, 2, 4, ... until one is not held (or max_rooms), then a
    bisection between the last held and the first not held. Yields each count tried."""
    lo, hi, k = 0, None, 1
    while hi is None:
        yield k
        if held(k):
            lo = k
            if k >= max_rooms:
                return
            k = min(2 * k, max_rooms)
        else:
            hi = k
    while hi - lo > max(1, lo // 16):  # to within ~6 %: finer is noise
        mid = (lo + hi) // 2
        yield mid
        if held(mid):
            lo = mid
        else:
            hi = mid


def run_rooms(base: Scene, cases: list[tuple[str, str, int]], frames: int, max_rooms: int,
              progress: Callable[[str], None]) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for backend, precision, n in cases:
        scene = room_scene(base, n)
        results: dict[int, dict[str, Any]] = {}

        def held(k: int, backend: str = backend, precision: str = precision, n: int = n,
                 scene: Scene = scene, results: dict[int, dict[str, Any]] = results) -> bool:
            times, mesh_us, threads = frame_times(scene, k, backend, precision, frames)
            results[k] = row(backend, precision, n, k, times, int(scene["sim"]["substeps"]),
                             mesh_us, threads)
            progress(f"{backend} {precision} n={n}: {k} rooms, p99 "
                     f"{results[k]['frame_us_p99']:.0f} us")
            return results[k]["held"]

        for _ in counts(max_rooms, held):
            pass
        rows += [results[k] for k in sorted(results)]
    return rows


def held_counts(rows: list[dict[str, Any]]) -> dict[tuple[str, str, int], int]:
    """The largest room count held per (backend, precision, n): 0 when none was."""
    best: dict[tuple[str, str, int], int] = {}
    for r in rows:
        key = (r["backend"], r["precision"], r["n"])
        best.setdefault(key, 0)
        if r["held"]:
            best[key] = max(best[key], r["rooms"])
    return best


def print_rooms(rows: list[dict[str, Any]]) -> None:
    print(f"{'backend':8} {'precision':9} {'n':>5} {'rooms':>6} {'threads':>7} {'substeps':>8} "
          f"{'p50 us':>8} {'p99 us':>8} {'mesh us/room':>12}  held")
    for r in rows:
        threads = "-" if r.get("threads") is None else str(r["threads"])
        print(f"{r['backend']:8} {r['precision']:9} {r['n']:5d} {r['rooms']:6d} "
              f"{threads:>7} {r['substeps']:8d} {r['frame_us_p50']:8.1f} "
              f"{r['frame_us_p99']:8.1f} {r['mesh_us_per_room']:12.2f}  "
              f"{'yes' if r['held'] else 'no'}")
    best = held_counts(rows)
    print("\nrooms held at 1 kHz (frame p99 <= 1 ms):")
    for (backend, precision, n), k in best.items():
        target = TARGETS.get((backend, precision, n))
        verdict = "" if target is None else (
            f"  (target {target}: {'met' if k >= target else 'missed'})")
        print(f"  {backend} {precision} n={n}: {k}{verdict}")
