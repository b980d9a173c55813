#!/usr/bin/env bash
# The accuracy study on the GPU: build with CUDA for the local card, run the accuracy and
# native-integrator tests with CLOTHBALL_REQUIRE_GPU=1 (a GPU skip is a failure), then
# `clothball accuracy` on the cuda backend, writing the table, JSON and plots into $OUT.
# Usage (on a machine with an NVIDIA GPU, from the repository root):
#   OUT=results bash tools/accuracy_gpu.sh [extra accuracy args, e.g. --sizes 20,40,80]
# Pure-Python wheels the machine lacks (tqdm) may be put in .whl/ beforehand.
OUT=${OUT:-accuracy-gpu-results}
source "$(dirname "$0")/gpu_build.sh"
cd /tmp  # import the installed package, not the source tree
tests_rc=0
if [ -z "${ACCURACY_SKIP_TESTS:-}" ]; then  # set it to skip the tests
OMP_NUM_THREADS=2 CLOTHBALL_REQUIRE_GPU=1 python3 -m pytest -q -p no:cacheprovider -p no:benchmark -n 8 -c "$OLDPWD/setup.cfg" \
  --rootdir "$OLDPWD" "$OLDPWD/tests/study/test_accuracy.py" \
  "$OLDPWD/tests/study/test_integrators_ref.py" "$OLDPWD/tests/study/test_cg_cost.py" \
  "$OLDPWD/tests/engine/test_integrators_native.py" \
  2>&1 | tee "$OUT/accuracy_tests.txt" | tail -5
tests_rc=${PIPESTATUS[0]}
fi
# What a CUDA implicit-Euler substep costs against the CG iterations it runs (issue 20).
python3 -m clothball.game.study.cg_cost --backend cuda --sizes 40,80 \
  --json "$OUT/cg_cost_gpu.json" 2>&1 | tee "$OUT/cg_cost_gpu.txt" | tail -12
acc_rc=0
if [ -z "${ACCURACY_SKIP_STUDY:-}" ]; then  # set it to run only the build, tests and CG cost
python3 -m clothball.game.cli accuracy --backend cuda --sizes 20,40,80 \
  --json "$OUT/accuracy_gpu.json" --plot "$OUT/accuracy_gpu.png" --fig4 "$OUT/fig4_gpu.png" "$@" \
  2>"$OUT/accuracy_gpu.err" | tee "$OUT/accuracy_gpu.txt"
acc_rc=${PIPESTATUS[0]}
fi
cd "$OLDPWD"
[ "$tests_rc" -eq 0 ] && exit "$acc_rc"
exit "$tests_rc"
