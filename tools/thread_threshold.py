"""Where a second CPU thread starts to pay for one cloth (``game/sim/threads.py``'s
``MIN_NODES_PER_THREAD``): time a substep with one thread and with two at each size, the
two alternated, and print their ratio. Run it on a quiet machine.

Usage: python tools/thread_threshold.py [--scene classic] [--sizes 32,64,...] [--rounds 3]
"""

from __future__ import annotations

import argparse
import statistics

from clothball.game.sim.cloth import Cloth
from clothball.game.sim.scene import Scene
from clothball.game.study.bench import time_substep


def main() -> None:
    p = argparse.ArgumentParser(prog="python tools/thread_threshold.py")
    p.add_argument("--scene", default="classic")
    p.add_argument("--sizes", default="32,48,64,90,128,181,256")
    p.add_argument("--rounds", type=int, default=3, help="alternated rounds (median taken)")
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args()
    print(f"scene {args.scene}, float32, the median of {args.rounds} alternated rounds")
    print("     n   nodes   1 thread us   2 threads us   2 / 1")
    for n in (int(s) for s in args.sizes.split(",")):
        scene = Scene.load(args.scene).with_changes(
            {"cloth": {"n": n}, "sim": {"precision": "float32"}})
        cloths = {t: Cloth(scene, "cpu", threads=t) for t in (1, 2)}
        got: dict[int, list[float]] = {1: [], 2: []}
        for r in range(args.rounds):
            for t in ((1, 2) if r % 2 == 0 else (2, 1)):
                got[t].append(time_substep(cloths[t], args.repeats))
        one, two = (statistics.median(got[t]) * 1e6 for t in (1, 2))
        print(f"{n:6d} {n * n:7d} {one:13.1f} {two:14.1f} {two / one:7.2f}")


if __name__ == "__main__":
    main()
