"""``clothball accuracy``: what accuracy costs in time (see ``accuracy.py`` for the study).

Prints the tables (short-horizon trajectory error and wall time per simulated ms, then the
long-horizon quantities, each against a float64 reference with a 16x smaller step, for each
integrator, precision, substep size and grid size), the fitted short-horizon orders, the
decorrelation time and the spatial error, and writes ``--json``, ``--plot`` (one panel per
metric, error against cost, log-log, Pareto front marked) and ``--fig4`` (the paper's
Fig. 4: ball height and corner force against time, and the corner force's spectrum).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

from ... import _native  # type: ignore[attr-defined]
from ..sim.cloth import cuda_unavailable_reason
from ..sim.scene import Scene, SceneError
from ..study.accuracy import (
    PRECISIONS,
    Plan,
    plot_error_vs_cost,
    plot_fig4,
    pyplot,
    run_study,
    table,
)
from ..study.bench import csv_list
from ..study.integrators_ref import INTEGRATORS

DEFAULT_SIZES = (20, 40)
QUICK_SIZES = (16,)
# The classic ball reaches the cloth at ~0.37 s and the corner force peaks at ~0.47 s.
QUICK_DURATION_S = 0.6


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default="classic", help="scene name or path (default classic)")
    p.add_argument("--sizes", help=f"comma-separated n (default {DEFAULT_SIZES})")
    p.add_argument("--integrators", default=",".join(INTEGRATORS), help="comma-separated")
    p.add_argument("--precisions", default="float32,float64", help="comma-separated")
    p.add_argument("--levels", type=int, default=None,
                   help="substep sizes per curve: the largest stable one, then halved (default 4)")
    p.add_argument("--duration", type=float, default=None,
                   help="simulated seconds of the Fig. 4 run (default 1.0)")
    p.add_argument("--backend", default="cpu", choices=("cpu", "cuda", "auto"))
    p.add_argument("--sag-sizes", default=None,
                   help="extra n for the Newton sag convergence (default 9,17,33)")
    p.add_argument("--no-energy", action="store_true", help="skip the undamped energy runs")
    p.add_argument("--no-sag", action="store_true", help="skip the steady-state sag runs")
    p.add_argument("--threads", type=int, default=None,
                   help="the CPU backend's threads (default: all cores; --quick: 1, its grid "
                        "is too small for threads to pay and a busy machine stalls them)")
    p.add_argument("--quick", action="store_true",
                   help=f"a short run through the impact: n = {QUICK_SIZES[0]}, "
                        f"{QUICK_DURATION_S:g} s, 3 step sizes")
    p.add_argument("--json", metavar="FILE", help="write the rows as JSON")
    p.add_argument("--plot", metavar="FILE.png", help="error against cost, log-log")
    p.add_argument("--fig4", metavar="FILE.png", help="the paper's Fig. 4")


def _ints(text: str, what: str) -> list[int]:
    try:
        vals = [int(t) for t in csv_list(text, what)]
    except ValueError as e:
        raise ValueError(f"--{what}: expected whole numbers: {e}") from None
    if any(not 3 <= v <= 4096 for v in vals):
        raise ValueError(f"--{what}: each n must be in 3..4096")
    return vals


def make_plan(args: argparse.Namespace) -> Plan:
    scene = Scene.load(args.scene)
    backend = args.backend
    why = cuda_unavailable_reason()
    if backend == "auto":
        backend = "cpu" if why else "cuda"
    elif backend == "cuda" and why:
        raise ValueError(f"--backend: cuda requested but {why}")
    sizes = _ints(args.sizes, "sizes") if args.sizes else list(
        QUICK_SIZES if args.quick else DEFAULT_SIZES)
    levels = args.levels if args.levels is not None else (3 if args.quick else 4)
    if not 2 <= levels <= 12:
        raise ValueError("--levels: must be in 2..12")
    duration = args.duration if args.duration is not None else (
        QUICK_DURATION_S if args.quick else 1.0)
    if not 0.0 < duration <= 60.0:
        raise ValueError("--duration: must be in (0, 60] seconds")
    threads = args.threads if args.threads is not None else (1 if args.quick else None)
    if threads is not None and not 1 <= threads <= 1024:
        raise ValueError("--threads: must be in 1..1024")
    sag_sizes = _ints(args.sag_sizes, "sag-sizes") if args.sag_sizes else (
        [] if args.quick else [9, 17, 33])
    return Plan(
        scene=scene, sizes=sizes,
        integrators=csv_list(args.integrators, "integrators", INTEGRATORS),
        precisions=csv_list(args.precisions, "precisions", PRECISIONS),
        levels=levels, duration_s=duration, backend=backend, sag_sizes=sag_sizes,
        energy=not args.no_energy, sag=not args.no_sag, decorrelation=True, threads=threads)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm  # noqa: PLC0415

    if args.plot or args.fig4:
        try:
            pyplot()
        except RuntimeError as e:  # before the study, not after minutes of it
            print(f"clothball accuracy: {e}", file=sys.stderr)
            return 2
    try:
        plan = make_plan(args)
    except (ValueError, SceneError) as e:
        print(f"clothball accuracy: {e}", file=sys.stderr)
        return 2
    total = plan.cases() + (len(plan.sag_sizes) if plan.sag else 0)
    with tqdm(total=total, desc="accuracy", unit="run", file=sys.stderr) as bar:
        def tick(label: str) -> None:
            bar.set_postfix_str(label[:60])
            bar.update(1)

        study = run_study(plan, tick)
    study.meta.update({"cpu_threads": _native.cpu_threads(), "machine": platform.node(),
                       "processor": platform.processor() or platform.machine(),
                       "argv": sys.argv[1:]})
    print(table(study))
    if args.json:
        Path(args.json).write_text(json.dumps(study.to_json(), indent=1))
        print(f"wrote {args.json}")
    if args.plot:
        plot_error_vs_cost(study, args.plot)
        print(f"wrote {args.plot}")
    if args.fig4:
        plot_fig4(study, args.fig4)
        print(f"wrote {args.fig4}")
    return 0
