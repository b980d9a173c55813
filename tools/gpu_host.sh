#!/usr/bin/env bash
# The GPU run of one `clothball host` (issue 33): build with CUDA, then `bench --load` on
# CUDA, default scene, real client rates, --workers 1 (one process) against --workers W
# (an engine and W-1 gateways on one port), the same machine in the same run; then the same
# at 1 kHz corners. Usage (on a GPU machine, websockets etc. carried in .whl/):
#   OUT=results bash tools/gpu_host.sh        # W (default 16), STEP, MAX, STEP1K, MAX1K, RUN_S
OUT=${OUT:-gpu-results}
source "$(dirname "$0")/gpu_build.sh"
load() {  # $1: label; the rest: bench flags
  local label=$1; shift
  timeout "${RUN_S:-110}" python3 -m clothball.game.cli bench --load --server-backend cuda \
    --scene default --load-seconds 5 --steps-past 1 --json "$OUT/load_$label.json" "$@" \
    2>>"$OUT/bench.err" | tee "$OUT/load_$label.txt" | tail -3
}
for w in 1 "${W:-16}"; do
  load "w$w" --workers "$w" --rooms-step "${STEP:-16}" --load-max-rooms "${MAX:-160}"
done
for w in 1 "${W:-16}"; do
  load "1khz_w$w" --workers "$w" --corner-rate 1000 --rooms-step "${STEP1K:-8}" \
    --load-max-rooms "${MAX1K:-48}"
done
