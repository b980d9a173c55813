#!/usr/bin/env bash
# The GPU run of one `clothball host` (issue 33): build with CUDA, optionally the server
# suites on the CUDA engine, then `bench --load` on CUDA, default scene, real client rates:
# --workers 1 (one process) against --workers W (an engine and W-1 gateways on one port),
# the same machine in the same run; at 120 Hz corners, then at 1 kHz.
# Usage (on a GPU machine, websockets etc. carried in .whl/):
#   OUT=results bash tools/gpu_host.sh
# Environment: W (default 16), STEP, MAX (120 Hz), STEP1K, MAX1K (1 kHz), RUN_S (each run's
# limit), RUNS (default "w1 wW"), RATES (default "120 1000"; empty: no load runs), TESTS (server test
# files run first on the CUDA engine, e.g. "tests/server/test_workers.py"), GPU_TESTS (test
# paths whose GPU cases run before them: -k "cuda or batch", or GPU_K), SKIP_BUILD=1 (a warm machine
# that has the build), FLAGS (more `bench --load` flags for every run, e.g. "--client-procs 6").
OUT=${OUT:-gpu-results}
if [ "${SKIP_BUILD:-0}" = 1 ]; then
  mkdir -p "$OUT"
  export PYTHONUNBUFFERED=1
  [ -d /tmp/site ] && export PYTHONPATH=${PYTHONPATH:+$PYTHONPATH:}/tmp/site
else
  source "$(dirname "$0")/gpu_build.sh"
fi
root=$PWD
python3 -c "from clothball import _native as n; print('MESH encoded in C++:', hasattr(n, 'encode_mesh_msg'))" \
  | tee -a "$OUT/gpu.txt"
gpu_pytest() {  # $1: output file, $2: seconds, $3: test paths (words); the rest: pytest flags
  local out=$1 limit=$2 paths=$3; shift 3
  # shellcheck disable=SC2046  # the paths are words
  (cd /tmp && OMP_NUM_THREADS=2 CLOTHBALL_REQUIRE_GPU=1 timeout "$limit" \
    python3 -m pytest -q -p no:cacheprovider -p no:benchmark -n "${TEST_WORKERS:-12}" \
    -c "$root/setup.cfg" --rootdir "$root" "$@" $(for t in $paths; do echo "$root/$t"; done) \
    >"$out" 2>&1)  # from /tmp: the installed package is imported, not the source tree
  echo "rc=$? $(tail -1 "$out")"
}
if [ -n "${GPU_TESTS:-}" ]; then
  echo "GPU tests: $(gpu_pytest "$OUT/gpu_tests.txt" "${GPU_TESTS_S:-200}" "$GPU_TESTS" -k "${GPU_K:-cuda or batch}")"
fi
if [ -n "${TESTS:-}" ]; then
  echo "server suites on CUDA: $(CLOTHBALL_TEST_BACKEND=cuda gpu_pytest "$OUT/server_cuda.txt" "${TESTS_S:-240}" "$TESTS")"
fi
load() {  # $1: label; the rest: bench flags
  local label=$1; shift
  timeout "${RUN_S:-110}" python3 -m clothball.game.cli bench --load --server-backend cuda \
    --scene default --load-seconds 5 --steps-past 1 --json "$OUT/load_$label.json" "$@" ${FLAGS:-} \
    2>>"$OUT/bench.err" | tee "$OUT/load_$label.txt" | tail -2
}
W=${W:-16}
for rate in ${RATES-120 1000}; do  # RATES="" (set, empty): tests only
  if [ "$rate" = 120 ]; then flags=(--rooms-step "${STEP:-16}" --load-max-rooms "${MAX:-160}")
  else flags=(--corner-rate "$rate" --rooms-step "${STEP1K:-8}" --load-max-rooms "${MAX1K:-48}")
  fi
  for run in ${RUNS:-w1 wW}; do
    case $run in
      w1) load "${rate}hz_w1" --workers 1 "${flags[@]}" ;;
      wW) load "${rate}hz_w$W" --workers "$W" "${flags[@]}" ;;
    esac
  done
done
