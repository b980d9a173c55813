#!/usr/bin/env bash
# The tiled frame's GPU check (issue 29): build with CUDA, its oracle tests with
# CLOTHBALL_REQUIRE_GPU=1, each frame path against the other at the sizes around the
# crossover (bench table, CLOTHBALL_CUDA_TILED=0 / 1), `bench --largest`, and a short
# summary table printed last. Usage (on a GPU machine): OUT=results bash tools/gpu_tiled.sh
# ROOMS=1 adds `bench --rooms` at n = 60 (the batch's path, which shares the substep code).
OUT=${OUT:-gpu-results}
source "$(dirname "$0")/gpu_build.sh"
root=$PWD
cd /tmp  # import the installed package, not the source tree
OMP_NUM_THREADS=2 CLOTHBALL_REQUIRE_GPU=1 timeout "${TESTS_S:-200}" python3 -m pytest -q -p no:cacheprovider \
  -p no:benchmark -n 8 -c "$root/setup.cfg" --rootdir "$root" \
  "$root/tests/engine/test_engine_vs_oracle.py" "$root/tests/engine/test_tiled_plan.py" \
  "$root/tests/engine/test_batch_gpu.py" -k "${TESTK:-cuda or gpu or tiled}" 2>&1 | tee "$OUT/tests.txt" | tail -4
tests_rc=${PIPESTATUS[0]}
cd "$root"
python3 -c "import clothball.game.cli.bench" 2>&1 | tail -3  # says why, if bench cannot load
bench=(python3 -m clothball.game.cli bench --backends cuda)
timeout "${LARGEST_S:-150}" "${bench[@]}" --largest --largest-frames "${LARGEST_FRAMES:-300}" --json "$OUT/largest.json" 2>>"$OUT/bench.err" | tee "$OUT/largest.txt" >/dev/null
for scene in classic default; do
  for tiled in 0 1; do
    CLOTHBALL_CUDA_TILED=$tiled timeout "${TABLE_S:-120}" "${bench[@]}" --scene $scene --repeats 3 \
      --sizes "${SIZES:-128,256,384,512,640,768,896,1024}" \
      --json "$OUT/table_${scene}_tiled$tiled.json" >"$OUT/table_${scene}_tiled$tiled.txt" 2>>"$OUT/bench.err"
  done
done
# Table 1's small rows (a launch a substep there), against the record in docs/benchmarks.
timeout "${TABLE_S:-60}" "${bench[@]}" --quick --precisions float32 --json "$OUT/table1_quick.json" \
  2>>"$OUT/bench.err" >"$OUT/table1_quick.txt"
[ "${ROOMS:-0}" = 1 ] && timeout 120 "${bench[@]}" --rooms --sizes 60 --rooms-frames 200 \
  --json "$OUT/rooms.json" 2>>"$OUT/bench.err" >"$OUT/rooms.txt"
python3 - "$OUT" <<'PY'
import json, pathlib, sys
out = pathlib.Path(sys.argv[1])
print("us/substep by path (substeps | tiled):")
for scene in ("classic", "default"):
    rows = {}
    for tiled in (0, 1):
        f = out / f"table_{scene}_tiled{tiled}.json"
        if f.exists():
            for r in json.loads(f.read_text())["rows"]:
                rows.setdefault((r["precision"], r["n"]), [None, None])[tiled] = r["substep_us"]
    for (prec, n), (a, b) in sorted(rows.items()):
        fa = f"{a:7.2f}" if a else "      -"
        fb = f"{b:7.2f}" if b else "      -"
        print(f"  {scene:8} {prec} n={n:5d} {fa} | {fb}")
PY
tail -12 "$OUT/largest.txt"
[ -f "$OUT/rooms.txt" ] && tail -4 "$OUT/rooms.txt"
grep -E "^[0-9]+ (passed|failed)|FAILED" "$OUT/tests.txt" | tail -8
tail -6 "$OUT/table1_quick.txt"
# What comes back is a few files: everything in one archive, the tests' log beside it.
tar czf /tmp/all.tgz -C "$OUT" --exclude tests.txt . \
  && find "$OUT" -type f ! -name tests.txt -delete && mv /tmp/all.tgz "$OUT/"
exit "$tests_rc"
