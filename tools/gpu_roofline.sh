#!/usr/bin/env bash
# Issue 41's GPU run: the kernels against their roofline, and what changed, A/B in one run.
# Usage (on a GPU machine): OUT=results bash tools/gpu_roofline.sh; STEPS="..." runs some
# of its steps (a later call on the machine still warm, the package installed, skips build):
#  build: the package with CUDA, and the lab programs beside it in two variants each (the
#    springs' reciprocal square root on and off, CB_SPRING_RSQRT);
#  tests: the CUDA oracle tests (CLOTHBALL_REQUIRE_GPU=1);
#  lab: the lab A/B alternated (lone cloth: launches a substep and the tiled frame; batch);
#  roofline: tools/gpu_roofline.py;
#  rooms: the rooms' fused frame, its block chosen against 1 024 threads
#    (CLOTHBALL_CUDA_FUSED_THREADS), alternated;
#  largest: `bench --largest --repeats 3`;
#  regress: Table 1's quick rows and `bench --rooms` at n = 60 (no regression);
#  plan: the tiled plan's compact tiles against the fewest nodes alone
#    (CLOTHBALL_CUDA_TILED_PLAN=work), alternated: its tests, Table 1 rows, --largest classic;
#  ncu: Nsight Compute on the tiled and fused frames, where it runs.
OUT=${OUT:-gpu-results}
STEPS=${STEPS:-build tests lab roofline rooms largest regress ncu}
# Steps write under a work folder, archived into $OUT after each step: what comes back
# from the machine is a few files, and a step cut off by the call's limit loses only itself.
FINAL=$OUT
OUT=/tmp/gpu-roofline-work
mkdir -p "$OUT" "$FINAL"
snap() { tar czf "$FINAL/${TAG:-run}.tgz" -C "$OUT" .; }
root=$PWD
# Pure-Python wheels the machine lacks (websockets, redis, ...) from .whl/, when no build
# step installs them (gpu_build.sh does).
if ! [[ " $STEPS " == *" build "* ]] && compgen -G ".whl/*.whl" >/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site
fi
export PYTHONUNBUFFERED=1
lab_nvcc=(nvcc -O3 -std=c++17 --expt-relaxed-constexpr -arch=sm_90 -Inative -prec-div=false
          -prec-sqrt=false)
bench=(python3 -m clothball.game.cli bench --backends cuda)
want() { [[ " $STEPS " == *" $1 "* ]]; }

if want build; then
  # The lab programs build on one core each while the package takes the rest.
  want lab && ( for v in 0 1; do
      "${lab_nvcc[@]}" -DCB_SPRING_RSQRT=$v tools/lab/substep_bench.cu -o /tmp/substep_rsqrt$v
      "${lab_nvcc[@]}" -DCB_SPRING_RSQRT=$v -Xcompiler -fopenmp tools/lab/batch_bench.cu -lgomp \
        -o /tmp/batch_rsqrt$v
    done ) >"$OUT/lab_build.log" 2>&1 &
  lab_pid=$!
  source "$(dirname "$0")/gpu_build.sh"
  wait $lab_pid; want lab && echo "lab build rc $?" | tee -a "$OUT/gpu.txt"
  snap
fi
if want tests; then
  cd /tmp
  xdist=(-n 8); python3 -c "import xdist" 2>/dev/null || xdist=()
  OMP_NUM_THREADS=2 CLOTHBALL_REQUIRE_GPU=1 timeout "${TESTS_S:-200}" python3 -m pytest -q \
    -p no:cacheprovider -p no:benchmark "${xdist[@]}" -c "$root/setup.cfg" --rootdir "$root" \
    "$root/tests/engine" -k "cuda or batch" 2>&1 | tee "$OUT/tests.txt" | tail -3
  cd "$root"
  snap
fi
if want lab; then  # the springs' rsqrt against sqrt and division, alternated, one build each
  python3 tools/lab/classic_configs.py 256 512 768 1024 > /tmp/lone.cfg
  python3 tools/lab/classic_configs.py 60 > /tmp/rooms.cfg
  for r in 1 2; do
    for v in 0 1; do
      echo "== rsqrt=$v run $r" >>"$OUT/lab_ab.txt"
      timeout 60 /tmp/substep_rsqrt$v /tmp/lone.cfg >>"$OUT/lab_ab.txt" 2>&1
      timeout 60 /tmp/batch_rsqrt$v /tmp/rooms.cfg 60 1024 1536 >>"$OUT/lab_ab.txt" 2>&1
    done
  done
  echo "--- lab A/B (lone: us a substep; batch: frame us)"; grep -v fingerprint "$OUT/lab_ab.txt"
  snap
fi
if want roofline; then
  timeout 150 python3 tools/gpu_roofline.py --json "$OUT/roofline.json" >"$OUT/roofline.txt" \
    2>"$OUT/roofline.err"
  cat "$OUT/roofline.txt"; tail -3 "$OUT/roofline.err"
  snap
fi
if want rooms; then  # the fused frame's block: chosen against 1 024 threads, alternated
  for r in 1 2; do
    for t in 1024 auto; do
      if [ $t = auto ]; then unset CLOTHBALL_CUDA_FUSED_THREADS; else export CLOTHBALL_CUDA_FUSED_THREADS=$t; fi
      timeout "${ROOMS_S:-75}" "${bench[@]}" --rooms --scene default --sizes 48 --rooms-frames 300 --max-rooms 2048 \
        --json "$OUT/rooms_default_${t}_$r.json" >"$OUT/rooms_default_${t}_$r.txt" 2>>"$OUT/bench.err"
      echo "default n=48 threads=$t run $r: $(tail -1 "$OUT/rooms_default_${t}_$r.txt")"
    done
  done
  unset CLOTHBALL_CUDA_FUSED_THREADS
  snap
fi
if want largest; then
  timeout "${LARGEST_S:-200}" "${bench[@]}" --largest --repeats 3 --json "$OUT/largest.json" >"$OUT/largest.txt" \
    2>>"$OUT/bench.err"
  tail -30 "$OUT/largest.txt"
  snap
fi
if want regress; then  # Table 1's quick rows and the classic rooms, against the record
  timeout 90 "${bench[@]}" --rooms --sizes 60 --rooms-frames 300 --json "$OUT/rooms_classic.json" \
    >"$OUT/rooms_classic.txt" 2>>"$OUT/bench.err"
  tail -3 "$OUT/rooms_classic.txt"
  timeout 60 "${bench[@]}" --quick --precisions float32 --json "$OUT/table1_quick.json" \
    >"$OUT/table1_quick.txt" 2>>"$OUT/bench.err"
  tail -8 "$OUT/table1_quick.txt"
  snap
fi
if want plan; then  # the tiled plan: compact tiles against the fewest nodes alone, alternated
  cd /tmp
  CLOTHBALL_REQUIRE_GPU=1 timeout 150 python3 -m pytest -q -p no:cacheprovider -p no:benchmark \
    -c "$root/setup.cfg" --rootdir "$root" "$root/tests/engine/test_engine_vs_oracle.py" \
    "$root/tests/engine/test_tiled_plan.py" -k "tiled" 2>&1 | tee "$OUT/plan_tests.txt" | tail -2
  cd "$root"
  for r in 1 2; do
    for mode in work compact; do
      CLOTHBALL_CUDA_TILED_PLAN=$mode timeout 60 "${bench[@]}" --scene classic --precisions float32 \
        --sizes 680,688,704,832,1024 --repeats 5 --json "$OUT/plan_table_${mode}_$r.json" \
        >"$OUT/plan_table_${mode}_$r.txt" 2>>"$OUT/bench.err"
      CLOTHBALL_CUDA_TILED_PLAN=$mode timeout 80 "${bench[@]}" --largest --scene classic --repeats 3 \
        --json "$OUT/plan_largest_${mode}_$r.json" >"$OUT/plan_largest_${mode}_$r.txt" 2>>"$OUT/bench.err"
      echo "plan=$mode run $r:"; grep -E "^ +[0-9]+ +cuda" "$OUT/plan_table_${mode}_$r.txt"
      grep -A3 "largest n held" "$OUT/plan_largest_${mode}_$r.txt" | cut -c1-110
    done
  done
  snap
fi
if want ncu; then
  # Nsight Compute on one launch of each hot kernel (where the machine lets it read the
  # counters): instructions issued, pipe use, occupancy.
  cat >/tmp/ncu_cases.py <<'PY'
import os
from clothball.game.sim.batch import ClothBatch
from clothball.game.sim.cloth import Cloth
from clothball.game.sim.scene import Scene
from clothball.game.study.rooms import room_scene
os.environ["CLOTHBALL_CUDA_TILED"] = "1"
for name, n in (("classic", 768), ("default", 512)):
    Cloth(room_scene(Scene.load(name), n), backend="cuda", precision="float32").step(1)
os.environ.pop("CLOTHBALL_CUDA_TILED")
for name, n in (("classic", 60), ("default", 48)):
    b = ClothBatch(room_scene(Scene.load(name), n), capacity=264, backend="cuda",
                   precision="float32")
    for _ in range(264):
        b.add()
    b.step(1)
PY
  timeout "${NCU_S:-100}" ncu --clock-control none -k regex:"tiled_frame|batch_frame" -c 4 \
    --section SpeedOfLight --section ComputeWorkloadAnalysis --section InstructionStats \
    --section Occupancy --section LaunchStats python3 /tmp/ncu_cases.py >"$OUT/ncu.txt" 2>&1
  echo "ncu rc $?" >>"$OUT/ncu.txt"
  grep -E "tiled_frame|batch_frame|Duration|Executed Ipc A|Issue Slots Busy|SM Busy|Registers Per|Achieved Occ|Block Size|ncu rc|==ERR" "$OUT/ncu.txt" | head -70
  snap
fi
tail -5 "$OUT/bench.err" 2>/dev/null
snap
