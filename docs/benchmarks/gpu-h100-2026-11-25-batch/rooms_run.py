"""The rooms bench for the CUDA backend (game.study.rooms, as `clothball bench --rooms`)
without the CLI's server imports. Usage: python3 rooms_run.py N FRAMES MAX_ROOMS; with
$OUT set it also writes $OUT/rooms_$TAG_nN.json."""
import json
import os
import sys

from clothball.game.sim.scene import Scene
from clothball.game.study import rooms

n = int(sys.argv[1]) if len(sys.argv) > 1 else 60
frames = int(sys.argv[2]) if len(sys.argv) > 2 else 300
max_rooms = int(sys.argv[3]) if len(sys.argv) > 3 else 4096
rows = rooms.run_rooms(Scene.load("classic"), [("cuda", "float32", n)], frames, max_rooms,
                       lambda s: print(s, flush=True))
rooms.print_rooms(rows)
out = os.environ.get("OUT")
if out:
    tag = os.environ.get("TAG", "batched")
    with open(f"{out}/rooms_{tag}_n{n}.json", "w") as f:
        json.dump({"rows": rows}, f, indent=1)
