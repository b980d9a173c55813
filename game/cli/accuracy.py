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

from ... import _native
from ..sim.cloth import cuda_unavailable_reason
from ..sim.scene import Scene, SceneError
from ..study import grid
from ..study.accuracy import (
    PRECISIONS,
    Plan,
    plot_error_vs_cost,
    plot_fig4,
    pyplot,
    run_study,
    table,
)
from ..study.bench import csv_ints, csv_list
from ..study.integrators_ref import INTEGRATORS

DEFAULT_SIZES = (20, 40)
GRID_SIZES = (13, 17, 25, 33)
GRID_REFERENCE_SIZES = (13, 25, 49)  # CPU-sized; on a GPU 129, 257, 513
QUICK_SIZES = (16,)
# The classic ball reaches the cloth at ~0.37 s and the corner force peaks at ~0.47 s.
QUICK_DURATION_S = 0.6


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default=None,
                   help="scene name or path (default classic; --grid: default)")
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
    g = p.add_argument_group(
        "the grid (--grid)", "n and the step together: each candidate's error against a "
        "Richardson-extrapolated high-n reference (game.study.grid, docs/accuracy.md)")
    g.add_argument("--grid", action="store_true",
                   help="run the grid study instead (default scene: default)")
    g.add_argument("--grid-sizes", default=None,
                   help=f"candidate n (default {','.join(map(str, GRID_SIZES))})")
    g.add_argument("--reference-sizes", default=None,
                   help="n of the reference, spacings halving (default "
                        f"{','.join(map(str, GRID_REFERENCE_SIZES))}; a GPU: e.g. 129,257,513)")
    g.add_argument("--steps", default="1,2,4",
                   help="substeps per frame as multiples of the stability bound's (default 1,2,4)")
    g.add_argument("--per-node", action="store_true",
                   help="also run the scene in per-node units (its per-node values at its n, "
                        "fixed on every grid): how much of the grid's error is the units")
    g.add_argument("--game-start", action="store_true",
                   help="with --grid: the game's start instead (game.study.gamestart): the "
                        "ball's and the centre's heights over 1.5 s on each n (--grid-sizes, "
                        "default 13,25,49,97), their distances between grids whose spacing "
                        "halves, sag, hand force, lowest point, rebound and observed orders; "
                        "every shipped scene, or --scene (docs/accuracy.md: the game's start)")
    p.add_argument("--json", metavar="FILE", help="write the rows as JSON")
    p.add_argument("--plot", metavar="FILE.png", help="error against cost, log-log")
    p.add_argument("--fig4", metavar="FILE.png", help="the paper's Fig. 4")


def _ints(text: str, what: str) -> list[int]:
    return csv_ints(text, what, 3, 4096)


def make_plan(args: argparse.Namespace) -> Plan:
    scene = Scene.load(args.scene or "classic")
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


def run_grid(args: argparse.Namespace) -> int:
    """``--grid``: the grid study (``game.study.grid``), and with ``--per-node`` the same in
    per-node units."""
    from tqdm import tqdm  # noqa: PLC0415

    try:
        scene = Scene.load(args.scene or "default")
        sizes = _ints(args.grid_sizes, "grid-sizes") if args.grid_sizes else list(GRID_SIZES)
        refs = (_ints(args.reference_sizes, "reference-sizes") if args.reference_sizes
                else list(GRID_REFERENCE_SIZES))
        steps = csv_ints(args.steps, "steps", 1, 1024, "each multiple")
        if len(refs) < 2:
            raise ValueError("--reference-sizes: at least 2 (3 whose spacings halve fit the order)")
        backend = args.backend if args.backend != "auto" else (
            "cpu" if cuda_unavailable_reason() else "cuda")
        if backend == "cuda" and cuda_unavailable_reason():
            raise ValueError(f"--backend: cuda requested but {cuda_unavailable_reason()}")
        duration = args.duration if args.duration is not None else 1.5
        if not 0.0 < duration <= 60.0:
            raise ValueError("--duration: must be in (0, 60] seconds")
    except (ValueError, SceneError) as e:
        print(f"clothball accuracy: {e}", file=sys.stderr)
        return 2
    scenes = [scene] + ([grid.per_node_twin(scene)] if args.per_node else [])
    out = []
    total = len(scenes) * (len(refs) + len(sizes) * len(steps))
    with tqdm(total=total, desc="grid", unit="run", file=sys.stderr) as bar:
        def tick(label: str) -> None:
            bar.set_postfix_str(label[:60])
            bar.update(1)

        for s in scenes:
            study = grid.grid_study(s, sizes, refs, steps, backend=backend,
                                    duration_s=duration, threads=args.threads, progress=tick)
            print(f"scene {s.name}, {backend}, float64\n{grid.table(study)}\n")
            out.append(study.to_json())
    if args.json:
        Path(args.json).write_text(json.dumps({"argv": sys.argv[1:], "studies": out}, indent=1))
        print(f"wrote {args.json}")
    return 0


def run_game_start(args: argparse.Namespace) -> int:
    """``--grid --game-start``: the game's start on each grid (``game.study.gamestart``)."""
    from ..study import gamestart  # noqa: PLC0415

    argv = ["--sizes", args.grid_sizes or "13,25,49,97", "--threads", str(args.threads or 1),
            "--backend", "cpu" if args.backend == "auto" else args.backend]
    if args.scene:
        argv += ["--scenes", args.scene]
    if args.json:
        argv += ["--json", args.json]
    return gamestart.main(argv)


def run(args: argparse.Namespace) -> int:
    if args.grid and args.game_start:
        return run_game_start(args)
    if args.grid:
        return run_grid(args)
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
