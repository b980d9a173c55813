#!/usr/bin/env bash
# One GPU call for a session's closing figures: build with CUDA, the engine, study and frame
# loop tests with CLOTHBALL_REQUIRE_GPU=1, the server suites on the CUDA engine, then one
# host's load (an engine and W-1 gateways with lanes, tools/gpu_host.sh) at 120 Hz and
# 1 kHz corners, and one room's server CPU with the CUDA batch's two ways of waiting for a
# frame (CLOTHBALL_CUDA_WAIT=spin|block). Usage: OUT=results bash tools/gpu_final.sh
OUT=${OUT:-gpu-results}
source "$(dirname "$0")/gpu_build.sh"
root=$PWD
cd /tmp  # import the installed package, not the source tree
OMP_NUM_THREADS=2 CLOTHBALL_REQUIRE_GPU=1 timeout "${ENGINE_S:-150}" python3 -m pytest -q \
  -p no:cacheprovider -p no:benchmark -n 12 -c "$root/setup.cfg" --rootdir "$root" \
  "$root/tests/engine" "$root/tests/study" "$root/tests/server/test_frame_loop.py" \
  "$root/tests/server/test_corner_msg.py" >"$OUT/gpu_tests.txt" 2>&1
echo "engine, study, frame loop on CUDA: rc=$? $(tail -1 "$OUT/gpu_tests.txt")"
cd "$root"
SKIP_BUILD=1 TESTS="${TESTS:-tests/server/test_workers.py tests/server/test_gateway.py
  tests/server/test_server_play.py tests/server/test_server_reconnect.py
  tests/server/test_faults.py tests/server/test_hostile_input.py tests/server/test_metrics.py
  tests/server/test_recording.py tests/server/test_server_fastpaths.py
  tests/server/test_server_match.py}" TESTS_S=100 RATES=120 RUNS=wW STEP=32 MAX=192 \
  RUN_S=140 bash tools/gpu_host.sh
SKIP_BUILD=1 RATES=1000 RUNS=wW STEP1K=8 MAX1K=64 RUN_S=90 bash tools/gpu_host.sh
for k in 1 2; do
  for w in spin block; do
    CLOTHBALL_CUDA_WAIT=$w timeout 40 python3 -m clothball.game.cli bench --load --workers 1 \
      --scene default --server-backend cuda --rooms-step 1 --load-max-rooms 1 \
      --load-seconds 5 --steps-past 0 2>&1 \
      | grep -E "^ +1 rooms" | sed "s/^/$w $k: /" | tee -a "$OUT/cuda_wait.txt"
  done
done
rm -f "$OUT/build.log" "$OUT"/load_*.txt
