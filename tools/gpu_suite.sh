#!/usr/bin/env bash
# The GPU run: build with CUDA for the local card, run the engine tests with
# CLOTHBALL_REQUIRE_GPU=1 (a GPU skip is a failure), then the benchmarks.
# Usage (on a machine with an NVIDIA GPU and no network):
#   OUT=results bash tools/gpu_suite.sh [bench args...]
# LAB=1 adds the launch-overlap A/B, the lab programs and the CPU effects bench.
# Pure-Python wheels the machine lacks (tqdm) may be put in .whl/ beforehand.
OUT=${OUT:-gpu-results}
source "$(dirname "$0")/gpu_build.sh"
cd /tmp  # import the installed package, not the source tree
# The engine's tests and the study's (both backends), spread over 8 workers. Two OpenMP
# threads a worker: 8 workers of 16 threads each oversubscribe the cores and the CPU
# engine's spinning barriers crawl (a whole run did not finish in 10 minutes).
OMP_NUM_THREADS=2 CLOTHBALL_REQUIRE_GPU=1 python3 -m pytest -q -p no:cacheprovider -p no:benchmark -n 8 \
  -c "$OLDPWD/setup.cfg" --rootdir "$OLDPWD" "$OLDPWD/tests/engine" "$OLDPWD/tests/study" \
  2>&1 | tee "$OUT/gpu_tests.txt" | tail -5
tests_rc=${PIPESTATUS[0]}
cd "$OLDPWD"
python3 -m clothball.game.cli bench --backends cuda --json "$OUT/bench_gpu.json" "$@" 2>"$OUT/bench_gpu.err" \
  | tee "$OUT/bench_gpu.txt"
# Rooms one engine holds at 1 kHz (ClothBatch), CUDA and the 16 CPU cores.
python3 -m clothball.game.cli bench --rooms --backends cuda,cpu --sizes 16,60 \
  --json "$OUT/rooms.json" 2>>"$OUT/bench_gpu.err" | tee "$OUT/rooms.txt"
python3 -m clothball.game.cli bench --effects --backends cuda --json "$OUT/effects_gpu.json" \
  2>>"$OUT/bench_gpu.err" | tee "$OUT/effects_gpu.txt"
# The largest cloth one engine steps at 1 kHz, per scene and precision (issue 29).
python3 -m clothball.game.cli bench --largest --backends cuda --json "$OUT/largest.json" \
  2>>"$OUT/bench_gpu.err" | tee "$OUT/largest.txt"
[ "${LAB:-0}" = 1 ] || exit "$tests_rc"  # LAB=1: also the launch A/B and the lab programs
# What overlapping launches (programmatic dependent launch) save: the small sizes again
# with them off.
CLOTHBALL_CUDA_OVERLAP=0 python3 -m clothball.game.cli bench --backends cuda \
  --precisions float32 --sizes 25,50,85,100,135,150,200,250 \
  --json "$OUT/bench_gpu_no_overlap.json" 2>>"$OUT/bench_gpu.err" | tee "$OUT/bench_gpu_no_overlap.txt"
# The lab programs (tools/lab/), built as the package's cloth unit is (native/CMakeLists.txt).
lab_nvcc=(nvcc -O3 -std=c++17 --expt-relaxed-constexpr -arch=sm_90 -Inative)
# The plane layout's streaming ceiling at large n.
"${lab_nvcc[@]}" tools/lab/stream_ceiling.cu -o /tmp/stream_ceiling \
  && /tmp/stream_ceiling | tee "$OUT/stream_ceiling.txt"
# The same backend timed with no Python, and its state fingerprint.
python3 tools/lab/classic_configs.py > "$OUT/classic.cfg" \
  && "${lab_nvcc[@]}" -prec-div=false -prec-sqrt=false tools/lab/substep_bench.cu \
    -o /tmp/substep_bench && /tmp/substep_bench "$OUT/classic.cfg" | tee "$OUT/substep_bench.txt"
# ClothBatch's CUDA engine with no Python: the rooms bench's frame at n = 60, split from
# Python's part.
python3 tools/lab/classic_configs.py 16 60 > "$OUT/rooms.cfg" \
  && "${lab_nvcc[@]}" -prec-div=false -prec-sqrt=false -Xcompiler -fopenmp \
    tools/lab/batch_bench.cu -lgomp -o /tmp/batch_bench \
  && /tmp/batch_bench "$OUT/rooms.cfg" 60 | tee "$OUT/batch_bench.txt"
# The CPU backend's effect costs on two quiet cores of this machine (the development
# machine is shared, and small CPU rows scatter there).
OMP_NUM_THREADS=2 taskset -c 0,1 python3 -m clothball.game.cli bench --effects --backends cpu \
  --json "$OUT/effects_cpu.json" 2>>"$OUT/bench_gpu.err" | tee "$OUT/effects_cpu.txt"
exit "$tests_rc"
