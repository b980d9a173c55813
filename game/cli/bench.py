"""``clothball bench``: time per substep (the paper's Table 1 re-measured, ``--effects``),
or the game server under load (``--server``, ``--load``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ... import _native  # type: ignore[attr-defined]
from ...server import loadbench
from ..sim.scene import SceneError
from ..study.bench import (
    gpu_target_verdicts,
    print_effects,
    print_skip_check,
    print_table,
    run_effects,
    run_table,
)


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="a short run: few sizes, few repeats")
    p.add_argument("--json", metavar="FILE", help="also write the rows as JSON")
    p.add_argument("--scene", default="classic", help="scene name or path (default classic)")
    p.add_argument("--sizes", help="comma-separated n values (default: the paper's sizes)")
    p.add_argument("--backends", default="auto", help="cpu,cuda or auto (every one present)")
    p.add_argument("--precisions", default="float32,float64", help="float32,float64")
    p.add_argument("--repeats", type=int, default=None, help="timed repeats (median taken)")
    p.add_argument(
        "--effects",
        action="store_true",
        help="time each effect alone and added one at a time (on --scene, default classic)",
    )
    p.add_argument(
        "--server", action="store_true", help="benchmark the game server instead (see --help)"
    )
    p.add_argument(
        "--load", action="store_true",
        help="how many rooms (4 players at 1 kHz + spectators) the server holds within target",
    )
    loadbench.configure_server_flags(p)


def run(args: argparse.Namespace) -> int:
    if args.server or args.load:
        return loadbench.run_load(args) if args.load else loadbench.run(args)
    if args.effects:
        try:
            rows = run_effects(args)
        except (ValueError, SceneError) as e:
            print(f"clothball bench: {e}", file=sys.stderr)
            return 2
        print_effects(rows)
        print("\nball contact skipped while the ball is off the cloth:")
        print_skip_check(rows)
        if args.json:
            Path(args.json).write_text(json.dumps({"rows": rows, "argv": sys.argv[1:]}, indent=2))
            print(f"wrote {args.json}")
        return 0
    try:
        rows = run_table(args)
    except (ValueError, SceneError) as e:
        print(f"clothball bench: {e}", file=sys.stderr)
        return 2
    copy_gbs = None
    if any(r["backend"] == "cuda" for r in rows):
        copy_gbs = _native.cuda_copy_bandwidth_gbs(1 << 30)
        print(f"device-to-device copy: {copy_gbs:.0f} GB/s (read + write)")
    print_table(rows, copy_gbs)
    verdicts = gpu_target_verdicts(rows, copy_gbs)
    if verdicts:
        print("\nissue 2's GPU targets (stated for an H100):")
        for line in verdicts:
            print("  " + line)
    if args.json:
        out = {"rows": rows, "copy_gbs": copy_gbs, "argv": sys.argv[1:]}
        Path(args.json).write_text(json.dumps(out, indent=2))
        print(f"wrote {args.json}")
    return 0
