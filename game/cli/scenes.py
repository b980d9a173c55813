"""``clothball scenes``: list the shipped scenes."""

from __future__ import annotations

import argparse

from ..sim.scene import Scene, available, schema_markdown


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--markdown", action="store_true", help="print the scene key reference")


def run(args: argparse.Namespace) -> int:
    if args.markdown:
        print(schema_markdown())
        return 0
    for name in available():
        s = Scene.load(name)
        print(f"{name:12} n={s.n:<5} effects: {', '.join(sorted(s.effects))}")
    return 0
