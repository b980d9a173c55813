"""A frame's CPU time per scene on one thread: ``python tools/step_time.py SCENE...``
(n = 48; the median of 7 runs of 50 frames after 20 of warm-up). For A/B comparisons of
the CPU backend between two builds, run one after the other on the same machine."""

import statistics
import sys
import time

from clothball.game.sim.cloth import Cloth
from clothball.game.sim.scene import Scene

for name in sys.argv[1:]:
    cloth = Cloth(Scene.load(name).with_changes({"cloth": {"n": 48}}), "cpu", threads=1)
    cloth.step(20)
    times = []
    for _ in range(7):
        t = time.perf_counter()
        cloth.step(50)
        times.append((time.perf_counter() - t) / 50)
    print(f"{name:8s} median {statistics.median(times) * 1e6:8.1f} us a frame")
