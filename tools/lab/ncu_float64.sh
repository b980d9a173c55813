source tools/gpu_build.sh > $OUT/build.txt 2>&1
cat >/tmp/ncu64.py <<'PY'
import os
from clothball.game.sim.cloth import Cloth
from clothball.game.sim.scene import Scene
from clothball.game.study.rooms import room_scene
os.environ["CLOTHBALL_CUDA_TILED"] = "1"
for name, n in (("classic", 640), ("default", 384)):
    c = Cloth(room_scene(Scene.load(name), n), backend="cuda", precision="float64")
    print(name, n, "substeps", c.substeps, c.engine_path, flush=True)
    c.step(1)
PY
timeout 200 ncu --clock-control none -k regex:"tiled_frame" -c 2 --section SpeedOfLight --section InstructionStats --section Occupancy --section LaunchStats python3 /tmp/ncu64.py > $OUT/ncu64.txt 2>&1; echo "ncu rc $?" >> $OUT/ncu64.txt
grep -E "substeps|tiled_frame|Duration|Executed Instructions  |Executed Ipc A|Issue Slots Busy|Registers Per|Achieved Occ|Block Size|Grid Size|ncu rc|==ERR" $OUT/ncu64.txt | head -40
