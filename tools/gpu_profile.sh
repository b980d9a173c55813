#!/usr/bin/env bash
# Where the engine's Python threads spend their time under load, on the GPU machine: one
# host (`bench --load`, CUDA, default scene) held at ROOMS rooms while py-spy samples the
# engine process (every thread, busy samples only, native frames off) for PROFILE_S seconds, after the step's
# rooms are set up. Writes $OUT/engine_profile.txt (py-spy's collapsed stacks, with thread
# names), $OUT/engine_dump.txt (one dump of every thread) and the bench's rows.
# Needs a py-spy wheel in .prof/ (pip download py-spy --no-deps --only-binary=:all:
# --platform manylinux2014_x86_64 -d .prof) and the build of tools/gpu_ab.sh (BUILD=head).
# Usage: OUT=results ROOMS=256 bash tools/gpu_profile.sh
OUT=${OUT:-gpu-results}
mkdir -p "$OUT"
python3 -m pip install -q --no-index --no-deps --target /tmp/pyspy .prof/*.whl
SPY=/tmp/pyspy/bin/py-spy
ROOMS=${ROOMS:-256}
cd /tmp || exit 1
PYTHONPATH=/tmp/head-site:/tmp/site python3 -m clothball.game.cli bench --load \
  --server-backend cuda --workers "${W:-16}" --scene default --rooms-step "$ROOMS" \
  --load-max-rooms "$ROOMS" --load-seconds "${LOAD_S:-40}" --steps-past 0 \
  --client-procs "${PROCS:-6}" ${CPUS:-} --json "$OUT/profile_bench.json" \
  >"$OUT/profile_bench.txt" 2>&1 &
bench=$!
for _ in $(seq 300); do grep -q " 1 rooms" "$OUT/profile_bench.txt" 2>/dev/null && break; sleep 1; done
sleep "${SETUP_S:-45}"  # the step's rooms joined
engine=$(pgrep -f -- "--public-port" | head -1)
echo "engine pid $engine; $(uptime)"
$SPY dump --pid "$engine" >"$OUT/engine_dump.txt" 2>&1
$SPY record --pid "$engine" --duration "${PROFILE_S:-20}" --rate 200 --threads \
  --format raw --output "$OUT/engine_profile.txt" --nonblocking >"$OUT/pyspy.log" 2>&1
wait $bench
tail -8 "$OUT/profile_bench.txt"
