#!/usr/bin/env bash
# The GPU run of the server's frame loop (issue 32): build with CUDA, the engine, study and
# frame-loop tests with CLOTHBALL_REQUIRE_GPU=1, the rooms one engine holds, and the load
# bench over one server process on CUDA.
# Usage (on a machine with an NVIDIA GPU; websockets etc. carried in .whl/):
#   OUT=results bash tools/gpu_server.sh
# TESTS: the test paths (default tests/engine tests/study and the frame loop's); BASE: a
# source tree (e.g. `git archive` of an older commit) built beside this one, whose
# `bench --rooms` alternates with this tree's (REPEATS times) on the same machine.
# CLOTHBALL_TEST_BACKEND=cuda with TESTS="tests/server/..." runs the server suites on the CUDA
# engine (tests/server/conftest.py).
OUT=${OUT:-gpu-results}
mkdir -p "$OUT/run"
if [ -n "${BASE:-}" ]; then
  python3 -m pip install -q --no-build-isolation --no-deps -Cbuild-dir=/tmp/cb-base \
    -Ccmake.define.CLOTHBALL_CUDA=ON -Ccmake.define.CMAKE_CUDA_ARCHITECTURES=90 \
    --target /tmp/base "$BASE" >"$OUT/run/build_base.log" 2>&1 &
  base_build=$!
fi
source "$(dirname "$0")/gpu_build.sh"
root=$PWD
tests=${TESTS:-tests/engine tests/study tests/server/test_frame_loop.py}
cd /tmp  # import the installed package, not the source tree
# shellcheck disable=SC2086  # the paths are words
OMP_NUM_THREADS=2 CLOTHBALL_REQUIRE_GPU=1 timeout "${TESTS_S:-300}" python3 -m pytest -q \
  -p no:cacheprovider -p no:benchmark -n 8 -c "$root/setup.cfg" --rootdir "$root" \
  $(for t in $tests; do echo "$root/$t"; done) 2>&1 | tee "$OUT/run/gpu_tests.txt" | tail -8
tests_rc=${PIPESTATUS[0]}
cd "$root"
rooms() {  # $1: label; the rest: environment for the command
  local label=$1; shift
  env "$@" timeout 120 python3 -m clothball.game.cli bench --rooms --backends cuda \
    --sizes "${ROOMS_SIZES:-16,60}" --json "$OUT/run/rooms_$label.json" \
    2>>"$OUT/run/bench.err" | tee "$OUT/run/rooms_$label.txt" | tail -3
}
if [ -n "${BASE:-}" ]; then
  wait "$base_build" || { tail -20 "$OUT/run/build_base.log"; exit 1; }
  for k in $(seq "${REPEATS:-2}"); do
    rooms "head_$k" PYTHONPATH="${PYTHONPATH:-}"
    rooms "base_$k" PYTHONPATH="/tmp/base${PYTHONPATH:+:$PYTHONPATH}"
  done
else
  rooms head PYTHONPATH="${PYTHONPATH:-}"
fi
timeout "${LOAD_S:-240}" python3 -m clothball.game.cli bench --load --server-backend cuda \
  --workers 1 --scene default --rooms-step "${ROOMS_STEP:-8}" \
  --load-max-rooms "${MAX_ROOMS:-64}" --load-seconds 5 --steps-past 1 \
  --json "$OUT/run/load_cuda.json" 2>>"$OUT/run/bench.err" \
  | tee "$OUT/run/load_cuda.txt" | tail -4
tar czf "$OUT/results.tgz" -C "$OUT" run
exit "$tests_rc"
