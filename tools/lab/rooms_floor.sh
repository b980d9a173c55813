#!/usr/bin/env bash
# Issue 41: the fused rooms' frame's floor a substep. Classic rooms of 1 024-thread blocks
# (CLOTHBALL_CUDA_FUSED_THREADS=1024, as n = 60 takes), at n = 4-16 where the nodes cost
# next to nothing, against n = 60, on one wave of slots (132) and on 1 024; µs a substep
# by tools/gpu_roofline.py's rooms(). Usage (a CUDA machine): OUT=results bash tools/lab/rooms_floor.sh
source "$(dirname "$0")/../gpu_build.sh" > "$OUT/build.txt" 2>&1
CLOTHBALL_CUDA_FUSED_THREADS=1024 PYTHONPATH="tools:${PYTHONPATH:-}" python3 - <<'PY' | tee "$OUT/rooms_floor.txt"
from gpu_roofline import rooms
from clothball.game.sim.scene import Scene
from clothball.game.study.rooms import room_scene
for n in (4, 8, 16, 60):
    for slots in (132, 1024):
        for _ in range(2):
            us, substeps = rooms(room_scene(Scene.load("classic"), n), "float32", slots)
            print(f"classic n = {n}, {slots} slots, {substeps} substeps: {us:.2f} us a substep",
                  flush=True)
PY
