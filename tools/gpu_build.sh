# Sourced by the GPU scripts: set up $OUT, carried wheels, and build clothball with CUDA
# for the local card (sm_90). Leaves the working directory at the repository root.
set -uo pipefail
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
if compgen -G ".whl/*.whl" >/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site
fi
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv | tee "$OUT/gpu.txt"
build_start=$SECONDS
python3 -m pip install -q --no-build-isolation --no-deps -Cbuild-dir=/tmp/cb-build \
  -Ccmake.define.CLOTHBALL_CUDA=ON -Ccmake.define.CMAKE_CUDA_ARCHITECTURES=90 . \
  >"$OUT/build.log" 2>&1 || { tail -40 "$OUT/build.log"; exit 1; }
echo "build (CPU + CUDA sm_90, $(nproc) cores): $((SECONDS - build_start)) s" | tee -a "$OUT/gpu.txt"
