"""Every shipped scene's cloth after 150 frames at n = 20, each integrator and precision,
on the CPU, into ``OUT.npz``: ``python tools/bit_dump.py OUT.npz`` with two builds, then
compare the arrays with ``numpy.array_equal`` (a change meant to keep the physics bit for
bit). A scene's bending stiffness is set to 0 where the build knows the key, so that a
build from before it compares alike."""

import sys

import numpy as np
from clothball.game.sim.cloth import Cloth
from clothball.game.sim.scene import INTEGRATORS, PRECISIONS, Scene

out = {}
for name in ("classic", "silk", "default", "windy"):
    for integrator in INTEGRATORS:
        for precision in PRECISIONS:
            scene = Scene.load(name).with_changes(
                {"cloth": {"n": 20}, "sim": {"integrator": integrator}})
            try:
                scene = scene.with_changes({"cloth": {"bending_stiffness": 0.0}})
            except (KeyError, ValueError):
                pass
            cloth = Cloth(scene, "cpu", precision=precision, threads=1)
            cloth.step(150)
            out[f"{name}-{integrator}-{precision}"] = np.asarray(cloth.positions())
np.savez(sys.argv[1], **out)
