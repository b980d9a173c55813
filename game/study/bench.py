"""Time per substep: the paper's Table 1 re-measured, and what each effect costs.

Median wall time per substep after warm-up, on the ``classic`` scene at each size, for the
CPU and (where there is one) the CUDA backend, in float32 and float64. Frames run with a
fixed substep count per size. That count is the automatic one for the scene at that size (a
fixed count would be unstable at large n, where the nodes are light), so every timed
substep is one a real run would take.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from typing import Any

from ..sim.cloth import Cloth, cuda_unavailable_reason
from ..sim.scene import Scene
from ..sim.stability import auto_substeps
from .integrators_ref import with_effects

# The paper's Table 1: n -> (CPU ms, GPU double ms, GPU single ms), one update each.
PAPER_TABLE1: dict[int, tuple[float, float, float]] = {
    25: (2.34, 0.38, 0.35),
    50: (9.38, 0.43, 0.36),
    85: (27.64, 1.01, 0.44),
    100: (37.79, 1.31, 0.85),
    135: (60.06, 1.91, 0.97),
    150: (84.98, 1.97, 1.25),
    200: (151.53, 3.27, 1.85),
    250: (240.59, 4.7, 2.24),
    300: (343.65, 5.92, 2.53),
    350: (468.66, 8.76, 3.15),
    400: (612.58, 10.56, 3.62),
    450: (771.68, 13.78, 4.11),
    500: (956.15, 15.92, 5.15),
}
SIZES = tuple(PAPER_TABLE1)
GPU_EXTRA_SIZES = (1024, 2048, 4096)
QUICK_SIZES = (25, 50, 100)
# Issue 2's GPU targets (stated for an H100, classic scene): float32 us per substep at every
# n <= SMALL_N, fraction of the copy bandwidth at every n >= LARGE_N, float64 / float32 at
# every n >= RATIO_N.
SMALL_N, SMALL_US = 256, 2.5
LARGE_N, LARGE_COPY = 2048, 0.80
RATIO_N, RATIO_MAX = 1024, 2.5


def csv_list(text: str, what: str, allowed: tuple[str, ...] | None = None) -> list[str]:
    items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise ValueError(f"--{what}: empty list")
    if allowed is not None:
        bad = [t for t in items if t not in allowed]
        if bad:
            raise ValueError(
                f"--{what}: unknown {', '.join(bad)}; choose from {', '.join(allowed)}"
            )
    return items


def csv_ints(text: str, what: str, lo: int, hi: int, each: str = "each n") -> list[int]:
    """A comma-separated list of whole numbers in lo..hi, else a ValueError naming --what."""
    try:
        vals = [int(t) for t in csv_list(text, what)]
    except ValueError as e:
        raise ValueError(f"--{what}: expected whole numbers: {e}") from None
    if any(not lo <= v <= hi for v in vals):
        raise ValueError(f"--{what}: {each} must be in {lo}..{hi}")
    return vals


def time_substep(cloth: Cloth, repeats: int, min_time: float = 0.02) -> float:
    """Median seconds per substep over ``repeats`` timed runs, after warm-up."""
    cloth.step(2)  # warm-up: first launch, graph capture, caches
    frames = 1
    while True:  # grow each run until it lasts at least min_time
        t0 = time.perf_counter()
        cloth.step(frames)
        elapsed = time.perf_counter() - t0
        if elapsed >= min_time or frames >= 1 << 16:
            break
        frames *= 2
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        cloth.step(frames)
        samples.append((time.perf_counter() - t0) / (frames * cloth.substeps))
    return statistics.median(samples)


def select_backends(args: argparse.Namespace) -> list[str]:
    """The backends --backends names ("auto": every one present here)."""
    cuda_missing = cuda_unavailable_reason()
    if args.backends == "auto":
        return ["cpu"] + ([] if cuda_missing else ["cuda"])
    backends = csv_list(args.backends, "backends", ("cpu", "cuda"))
    if "cuda" in backends and cuda_missing:
        raise ValueError(f"--backends: cuda requested but {cuda_missing}")
    return backends


def plan(args: argparse.Namespace) -> list[tuple[str, str, int]]:
    """The (backend, precision, n) cases to run, in order."""
    backends = select_backends(args)
    precisions = csv_list(args.precisions, "precisions", ("float32", "float64"))
    if args.sizes:
        sizes = csv_ints(args.sizes, "sizes", 2, 8192)
    else:
        sizes = list(QUICK_SIZES if args.quick else SIZES)
    cases = []
    for backend in backends:
        gpu_sizes = backend == "cuda" and not args.sizes and not args.quick
        extra = list(GPU_EXTRA_SIZES) if gpu_sizes else []
        for precision in precisions:
            for n in sizes + extra:
                cases.append((backend, precision, n))
    return cases


def run_table(args: argparse.Namespace) -> list[dict[str, Any]]:
    from tqdm import tqdm  # noqa: PLC0415

    base = Scene.load(args.scene)
    repeats = args.repeats or (3 if args.quick else 7)
    rows = []
    cases = plan(args)
    for backend, precision, n in tqdm(cases, desc="bench", unit="case", file=sys.stderr):
        sized = base.with_changes({"cloth": {"n": n}})
        scene = sized.with_changes({"sim": {"substeps": auto_substeps(sized)}})
        cloth = Cloth(scene, backend=backend, precision=precision)
        sec = time_substep(cloth, repeats)
        bytes_min = 12 * (4 if precision == "float32" else 8) * n * n
        rows.append(
            {
                "n": n,
                "backend": backend,
                "precision": precision,
                "substep_us": sec * 1e6,
                "scene": base.name,
                "effects": sorted(base.effects),
                "substeps_per_frame": cloth.substeps,
                "min_bytes_per_substep": bytes_min,
                "effective_gbs": bytes_min / sec / 1e9,
                "cpu_threads": cloth.threads,
            }
        )
        del cloth
    return rows


# The order effects are added in by --effects: the paper's set first, then the rest.
EFFECT_ORDER = (
    "structural",
    "gravity",
    "damping",
    "coupling",
    "ball",
    "shear",
    "bend",
    "wind",
    "strain_limit",
)


# Far below the cloth: no node can reach the ball, so its contact is skipped at run time.
BALL_OFF = {"ball": {"position": [0.0, -100.0, 0.0], "velocity": [0.0, 0.0, 0.0]}}
BALL_OFF_LABEL = "ball off the cloth"


def effect_cases(base: Scene) -> list[tuple[str, tuple[str, ...]]]:
    """(label, effect set) rows: each effect alone, then added one at a time, the scene as
    shipped, and (if it has a ball) the scene without the ball effect and the scene with
    the ball off the cloth, whose contact must then cost nothing."""
    cases = [(f"{e} alone", (e,)) for e in EFFECT_ORDER]
    for k in range(1, len(EFFECT_ORDER) + 1):
        label = EFFECT_ORDER[k - 1] if k == 1 else f"+ {EFFECT_ORDER[k - 1]}"
        cases.append((label, EFFECT_ORDER[:k]))
    shipped = tuple(sorted(base.effects))
    cases.append((f"{base.name} as shipped", shipped))
    if "ball" in shipped:
        cases.append((f"{base.name} without ball", tuple(e for e in shipped if e != "ball")))
        cases.append((f"{base.name}, {BALL_OFF_LABEL}", shipped))
    return cases


def run_effects(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Time per substep for each effect set of ``effect_cases`` on each backend.

    Every set runs at the same substep count (the one the full set needs), so that the
    rows differ only in the kernel. Each set is timed twice, in two separate passes over
    the list, to show how far two measurements of one kernel lie apart.
    """
    from tqdm import tqdm  # noqa: PLC0415

    base = Scene.load(args.scene)
    n = int(csv_list(args.sizes, "sizes")[0]) if args.sizes else base.n
    full = base.with_changes({"cloth": {"n": n}, "sim": {"effects": list(EFFECT_ORDER)}})
    substeps = auto_substeps(full)
    precisions = csv_list(args.precisions, "precisions", ("float32", "float64"))
    backends = select_backends(args)
    repeats = args.repeats or (3 if args.quick else 7)
    cases = effect_cases(base)
    rows = []
    jobs = [(b, p, c) for b in backends for p in precisions for c in cases]
    timings: dict[tuple[str, str, tuple[str, ...]], list[float]] = {}
    for _pass in range(2):
        progress = tqdm(jobs, desc=f"effects pass {_pass + 1}", unit="set", file=sys.stderr)
        for backend, precision, (label, effects) in progress:
            changes: dict[str, Any] = {
                "cloth": {"n": n},
                "sim": {"effects": list(effects), "substeps": substeps, "allow_unstable": True},
            }
            if label.endswith(BALL_OFF_LABEL):
                changes.update(BALL_OFF)
            # Without the keys of the base's effects this set leaves out (the default scene
            # sets k_shear, bending_stiffness, ...: a scene may not set an absent effect's).
            scene = with_effects(base, base.effects - set(effects)).with_changes(changes)
            with warnings.catch_warnings():  # every set runs at the full set's substeps
                warnings.simplefilter("ignore")
                cloth = Cloth(scene, backend=backend, precision=precision)
            timings.setdefault((backend, precision, label), []).append(
                time_substep(cloth, repeats) * 1e6
            )
    for backend, precision, (label, effects) in jobs:
        t = timings[(backend, precision, label)]
        rows.append(
            {
                "label": label,
                "effects": list(effects),
                "backend": backend,
                "precision": precision,
                "n": n,
                "substeps_per_frame": substeps,
                "substep_us": statistics.median(t),
                "pass_us": t,
                "pass_spread": abs(t[0] - t[1]) / min(t),
            }
        )
    return rows


def print_effects(rows: list[dict[str, Any]]) -> None:
    head = f"{'effects':<28} {'backend':>7} {'precision':>9} {'us/substep':>11}"
    print(f"{head} {'2-pass spread':>13}")
    for r in rows:
        print(
            f"{r['label']:<28} {r['backend']:>7} {r['precision']:>9} {r['substep_us']:>11.2f} "
            f"{r['pass_spread']:>12.1%}"
        )
    # What removing each effect saves, from the cumulative rows: T(with) - T(without).
    by = {
        (r["backend"], r["precision"], tuple(r["effects"])): r["substep_us"]
        for r in rows
        if not r["label"].endswith(BALL_OFF_LABEL)
    }
    print("\ncost of each effect on top of the ones before it (cumulative rows):")
    for (backend, precision, effects), t in by.items():
        k = len(effects)
        if effects == EFFECT_ORDER[:k] and k > 1:
            before = by[(backend, precision, EFFECT_ORDER[: k - 1])]
            print(
                f"  {backend:>4} {precision} {effects[-1]:<13} {t - before:+8.2f} us "
                f"({(t - before) / before:+.0%})"
            )


def print_skip_check(rows: list[dict[str, Any]]) -> None:
    """The ball-off row against the kernel compiled without the ball (the 3 % claim)."""
    by = {(r["backend"], r["precision"], r["label"]): r for r in rows}
    for (backend, precision, label), r in by.items():
        if not label.endswith(BALL_OFF_LABEL):
            continue
        name = label.split(",")[0]
        ref = by[(backend, precision, f"{name} without ball")]
        diff = r["substep_us"] / ref["substep_us"] - 1
        noise = max(r["pass_spread"], ref["pass_spread"])
        verdict = "within 3 %" if abs(diff) <= 0.03 else "NOT within 3 %"
        print(
            f"  {backend:>4} {precision} ball off the cloth {r['substep_us']:.2f} us vs "
            f"compiled without ball {ref['substep_us']:.2f} us: {diff:+.1%} ({verdict}; "
            f"2-pass spread up to {noise:.1%})"
        )


def print_table(rows: list[dict[str, Any]], copy_gbs: float | None) -> None:
    print(f"{'n':>6} {'backend':>7} {'precision':>9} {'threads':>7} {'us/substep':>11} "
          f"{'GB/s':>7}  paper (ms)")
    for r in rows:
        paper = PAPER_TABLE1.get(r["n"])
        note = ""
        if paper:
            cpu, dp, sp = paper
            ref = cpu if r["backend"] == "cpu" else (sp if r["precision"] == "float32" else dp)
            label = "CPU" if r["backend"] == "cpu" else "GPU " + r["precision"]
            speedup = ref * 1e3 / r["substep_us"]
            # (a busy machine's CPU row can fall below 1x: "0x faster" said nothing)
            note = (f"{label} {ref:g} ms -> {speedup:.0f}x faster" if speedup >= 1.5 else
                    f"{label} {ref:g} ms -> {speedup:.2g}x as fast")
        bw = r["effective_gbs"]
        extra = f" ({bw / copy_gbs:.1%} of copy)" if copy_gbs and r["backend"] == "cuda" else ""
        threads = "-" if r.get("cpu_threads") is None else str(r["cpu_threads"])
        print(
            f"{r['n']:>6} {r['backend']:>7} {r['precision']:>9} {threads:>7} "
            f"{r['substep_us']:>11.2f} {bw:>7.1f}  {note}{extra}"
        )


def gpu_target_verdicts(rows: list[dict[str, Any]], copy_gbs: float | None) -> list[str]:
    """One line per GPU target of issue 2 that the CUDA rows measure: the worst row against
    the target, and whether it is met. Targets whose sizes were not run are left out."""
    cuda = [r for r in rows if r["backend"] == "cuda"]
    us = {(r["n"], r["precision"]): r["substep_us"] for r in cuda}
    lines = []

    def verdict(ok: bool) -> str:
        return "met" if ok else "MISSED"

    small = [(v, n) for (n, prec), v in us.items() if prec == "float32" and n <= SMALL_N]
    if small:
        worst, n = max(small)
        lines.append(
            f"float32 <= {SMALL_US} us per substep at n <= {SMALL_N}: worst {worst:.2f} us "
            f"(n = {n}): {verdict(worst <= SMALL_US)}"
        )
    large = [(r["effective_gbs"] / copy_gbs, r["n"]) for r in cuda
             if copy_gbs and r["precision"] == "float32" and r["n"] >= LARGE_N]
    if large:
        worst, n = min(large)
        lines.append(
            f"float32 >= {LARGE_COPY:.0%} of copy at n >= {LARGE_N}: worst {worst:.1%} "
            f"(n = {n}): {verdict(worst >= LARGE_COPY)}"
        )
    ratios = [(us[(n, "float64")] / v, n) for (n, prec), v in us.items()
              if prec == "float32" and n >= RATIO_N and (n, "float64") in us]
    if ratios:
        worst, n = max(ratios)
        lines.append(
            f"float64 <= {RATIO_MAX}x float32 at n >= {RATIO_N}: worst {worst:.2f}x "
            f"(n = {n}): {verdict(worst <= RATIO_MAX)}"
        )
    return lines
