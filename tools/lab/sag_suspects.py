"""Lab: the static sag (and force on a hand at rest) of a scene over grids whose spacing
halves, with one suspect changed at a time (``--set`` as in game/study/gamestart.py), to
find what keeps the sag from converging at first order.

    python tools/lab/sag_suspects.py default --sizes 13,25,49,97 \
        --set coupling.grip_radius=0.1 --set cloth.k_bend=0.0
"""

from __future__ import annotations

import argparse

from clothball.game import Scene
from clothball.game.study.gamestart import scene_changes
from clothball.game.study.grid import observed_order, rest_state, sized


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--sizes", default="13,25,49,97")
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args()
    changes = scene_changes(args.set)
    base = Scene.load(args.scene)
    base = base.with_changes(changes) if changes else base
    ns = [int(x) for x in args.sizes.split(",")]
    sags, forces = [], []
    for n in ns:
        _, sag, force = rest_state(sized(base, n), "cpu", 1)
        sags.append(sag)
        forces.append(force)
    orders = [observed_order(*sags[k:k + 3]) for k in range(len(ns) - 2)]
    forders = [observed_order(*forces[k:k + 3]) for k in range(len(ns) - 2)]
    print(f"{args.scene} {' '.join(args.set)}")
    print("  sag mm  " + ", ".join(f"{1e3 * s:.2f}" for s in sags)
          + "  orders " + ", ".join(f"{o:.2f}" for o in orders))
    print("  force N " + ", ".join(f"{f:.4f}" for f in forces)
          + "  orders " + ", ".join(f"{o:.2f}" for o in forders))


if __name__ == "__main__":
    main()
