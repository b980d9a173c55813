"""How far the motion of test_engine_vs_oracle's cases exceeds their derived tolerance
(the spread of two float64 oracles started a float32 rounding apart, times 10), after
10-40 frames: the check there asks for more than 100. Run from the repository root:
``python tools/lab/oracle_spread.py [case ...]``."""

from __future__ import annotations

import sys

import numpy as np
from clothball.game import Cloth, ReferenceCloth

sys.path.insert(0, "tests/engine")
import test_engine_vs_oracle as T  # noqa: E402

FRAMES = (10, 20, 30, 40)


def main() -> None:
    for case in sys.argv[1:] or list(T.CASES):
        effects, extra = T.CASES[case]
        scene = T.scene_with(effects, **extra)
        substeps = Cloth(scene, backend="cpu", precision="float32").substeps
        hips = ReferenceCloth(scene).hips + T.HIPS_MOVE
        start = T._state(ReferenceCloth(scene))
        cells = []
        for frames in FRAMES:
            def drive(sim, scene=scene, frames=frames, substeps=substeps, hips=hips):
                T._drive(sim, scene, frames, substeps, hips)
            tol = T.allowed_drift(scene, "float32", substeps, hips, drive=drive)
            ref = ReferenceCloth(scene)
            drive(ref)
            moved = np.abs(T._state(ref) - start).max()
            cells.append(f"{frames} frames: tolerance {tol:.2g}, motion {moved / tol:.0f} of it")
        print(f"{case} ({substeps} substeps): " + " | ".join(cells), flush=True)


if __name__ == "__main__":
    main()
