"""Write the native engine's configuration of the ``classic`` scene at each bench size, one
line per size, for tools/lab/substep_bench.cu (which times the CUDA backend with no Python).

Usage: python tools/lab/classic_configs.py [n ...] > /tmp/classic.cfg (default: SIZES;
tools/lab/batch_bench.cu takes the room sizes, e.g. 16 60)
"""

from __future__ import annotations

import sys

from clothball.game import Cloth, Scene
from clothball.game.sim.config import native_config

SIZES = (25, 50, 85, 100, 135, 150, 200, 250, 300, 400, 500, 1024, 2048, 4096)
FIELDS = (
    "n rest_len node_mass k_struct k_shear k_bend struct_compress damping ball_radius "
    "ball_mass ball_k ball_damping ball_edges coupling_k effects"
).split()


def main() -> None:
    classic = Scene.load("classic")
    for n in [int(a) for a in sys.argv[1:]] or SIZES:
        scene = classic.with_changes({"cloth": {"n": n}})
        c = native_config(scene)
        cloth = Cloth(scene, backend="cpu", precision="float32") if n <= 256 else None
        substeps = cloth.substeps if cloth else _substeps(scene)
        ball = scene["ball"]
        vals = [f"{f}={float(getattr(c, f))!r}" for f in FIELDS]
        vals += [
            f"gravity={','.join(map(repr, c.gravity))}",
            f"height={scene['cloth']['height']!r}",
            f"substeps={substeps}",
            f"frame_dt={scene['sim']['frame_dt']!r}",
            f"ball={','.join(map(repr, [*ball['position'], *ball['velocity']]))}",
        ]
        sys.stdout.write(" ".join(vals) + "\n")


def _substeps(scene: Scene) -> int:
    from clothball.game.sim.stability import auto_substeps

    return auto_substeps(scene, 0.0)


if __name__ == "__main__":
    main()
