"""The CPU backend's speed targets, measured in one run on this machine:

1. at n = 64, time per substep of the CPU backend against a vectorised NumPy step of the
   same equations (the oracle, clothball.game.sim.oracle.ReferenceCloth);
2. substeps per second at n = 135.

Both on the classic scene, float32, at its automatic substep count. Medians of repeats.
Usage: python tools/cpu_targets.py
"""

from __future__ import annotations

import statistics
import time

from clothball import _native
from clothball.game import Cloth, ReferenceCloth, Scene
from clothball.game.sim.stability import auto_substeps
from clothball.game.study.bench import time_substep


def numpy_substep_s(scene: Scene, repeats: int = 7) -> float:
    ref = ReferenceCloth(scene)
    dt = scene["sim"]["frame_dt"] / auto_substeps(scene)
    ref.substep(dt)
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(20):
            ref.substep(dt)
        samples.append((time.perf_counter() - t0) / 20)
    return statistics.median(samples)


def main() -> None:
    base = Scene.load("classic")
    s64 = base.with_changes({"cloth": {"n": 64}})
    s64 = s64.with_changes({"sim": {"substeps": auto_substeps(s64)}})
    cpu64 = time_substep(Cloth(s64, backend="cpu", precision="float32"), 7)
    np64 = numpy_substep_s(s64)
    s135 = base.with_changes({"cloth": {"n": 135}})
    s135 = s135.with_changes({"sim": {"substeps": auto_substeps(s135)}})
    cpu135 = time_substep(Cloth(s135, backend="cpu", precision="float32"), 7)
    print(f"threads: {_native.cpu_threads()}")
    print(f"n=64:  CPU {cpu64 * 1e6:.1f} us/substep, NumPy {np64 * 1e6:.1f} us/substep "
          f"-> {np64 / cpu64:.1f}x (target >= 20x)")
    print(f"n=135: CPU {cpu135 * 1e6:.1f} us/substep -> {1 / cpu135:.0f} substeps/s "
          f"(target >= 3000)")


if __name__ == "__main__":
    main()
