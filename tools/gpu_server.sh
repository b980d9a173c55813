#!/usr/bin/env bash
# The GPU run of the server's frame loop (issue 32): build with CUDA, the engine, study and
# frame-loop tests with CLOTHBALL_REQUIRE_GPU=1, the rooms one engine holds, and the load
# bench over one server process on CUDA, the Python loop and the native one in the same run.
# Usage (on a machine with an NVIDIA GPU; websockets etc. carried in .whl/):
#   OUT=results bash tools/gpu_server.sh
OUT=${OUT:-gpu-results}
source "$(dirname "$0")/gpu_build.sh"
root=$PWD
cd /tmp  # import the installed package, not the source tree
OMP_NUM_THREADS=2 CLOTHBALL_REQUIRE_GPU=1 timeout "${TESTS_S:-300}" python3 -m pytest -q \
  -p no:cacheprovider -p no:benchmark -n 8 -c "$root/setup.cfg" --rootdir "$root" \
  "$root/tests/engine" "$root/tests/study" "$root/tests/server/test_frame_loop.py" \
  2>&1 | tee "$OUT/gpu_tests.txt" | tail -8
tests_rc=${PIPESTATUS[0]}
cd "$root"
timeout 120 python3 -m clothball.game.cli bench --rooms --backends cuda --sizes 16,60 \
  --json "$OUT/rooms.json" 2>>"$OUT/bench.err" | tee "$OUT/rooms.txt" | tail -6
for loop in python native; do
  timeout "${LOAD_S:-240}" python3 -m clothball.game.cli bench --load --server-backend cuda \
    --workers 1 --scene default --rooms-step "${ROOMS_STEP:-8}" \
    --load-max-rooms "${MAX_ROOMS:-64}" --load-seconds 5 --steps-past 1 --frame-loop "$loop" \
    --json "$OUT/load_cuda_$loop.json" 2>>"$OUT/bench.err" | tee "$OUT/load_cuda_$loop.txt" \
    | tail -4
done
exit "$tests_rc"
