#!/usr/bin/env bash
# A/B on the GPU machine, the same machine in one lease: this tree ("head") against a base
# commit's source carried in .base/ (`rm -rf .base && mkdir .base && git archive BASE | tar -x
# -C .base`, then carry .base and .whl), both built with CUDA for sm_90.
#   TWO_CORE="base head base head"  each: one process on 2 cores (taskset -c 2,3), the CPU
#       engine, `bench --load --workers 1 --scene default --server-n 16 --rooms-step 2`, the
#       2-core machine's no-regression check on a quiet machine (TWO_MAX rooms at most, 20;
#       TWO_S seconds a run, 150)
#   PAR_ROUNDS="base head base head/head base head base"  the same run, several at once: in
#       each round (rounds split by /) the i-th label on cores 2i+2,2i+3, the rounds in turn
#   HOST="base head"  each: one host on the GPU, `bench --load --workers $W --rooms-step $STEP
#       --load-max-rooms $MAX --client-procs $PROCS $CPUS` (CPUS: e.g. "--server-cpus 0-9
#       --client-cpus 10-15", the server and its load on cores of their own; EXTRA: more
#       bench flags, e.g. "--corner-rate 1000")
#   BENCH="ARGS;ARGS..." BENCH_LABELS="base head base head"  each label in turn runs
#       `clothball bench ARGS` once for each ARGS (the engine's own benches: Table 1, --rooms),
#       output in $OUT/bench_<i>_<j>_<label>.txt (BENCH_S seconds each, 300)
#   GPU_TESTS / TESTS  as in tools/gpu_host.sh, on head, first
#   SKIP_BUILD=1  a warm machine that has both builds (a second call within its warm time)
#   BUILD="head"  build only these (no base: no label may use it)
# A label "head:VAR=value" runs head with that environment variable set (an experiment); "mix"
# runs head's server with base's load-generator clients (on two cores the clients' own CPU
# is shared with the server's: mix against base compares the servers alone).
# Usage: OUT=results TWO_CORE="..." HOST="..." bash tools/gpu_ab.sh
OUT=${OUT:-gpu-results}
root=$PWD
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
if [ "${SKIP_BUILD:-0}" != 1 ]; then
  # Both builds into directories of their own, side by side (16 cores): the clothball
  # package has no __init__.py, so two installs on one path would mix.
  if compgen -G ".whl/*.whl" >/dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl
  fi
  nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv \
    | tee "$OUT/gpu.txt"
  start=$SECONDS
  for t in ${BUILD:-head base}; do
    src=.; [ $t = base ] && src=./.base
    python3 -m pip install -q --no-build-isolation --no-deps --target /tmp/$t-site \
      -Cbuild-dir=/tmp/cb-build-$t -Ccmake.define.CLOTHBALL_CUDA=ON \
      -Ccmake.define.CMAKE_CUDA_ARCHITECTURES=90 $src >"$OUT/build_$t.log" 2>&1 &
  done
  wait
  echo "builds (CPU + CUDA sm_90, both at once): $((SECONDS - start)) s" | tee -a "$OUT/gpu.txt"
fi
for t in ${BUILD:-head base}; do
  [ -d /tmp/$t-site/clothball ] || { echo "$t build failed"; tail -20 "$OUT/build_$t.log"; }
done
if [ -d .base/server/bench ] && [ -d /tmp/head-site/clothball ]; then
  rm -rf /tmp/mix-site && cp -r /tmp/head-site /tmp/mix-site &&
    cp .base/server/bench/benchclients.py /tmp/mix-site/clothball/server/bench/
fi
cd "$root" || exit 1
PYTHONPATH=/tmp/head-site SKIP_BUILD=1 RATES="" OUT=$OUT bash "$(dirname "$0")/gpu_host.sh"  # GPU_TESTS, TESTS (head)
cd /tmp || exit 1  # the installed packages are imported, not the source tree
as() {  # $1: label (base, head, head:VAR=value); the rest: the command
  local label=$1; shift
  case $label in
    base) env PYTHONPATH=/tmp/base-site:/tmp/site "$@" ;;
    mix) env PYTHONPATH=/tmp/mix-site:/tmp/site "$@" ;;
    head:*) env PYTHONPATH=/tmp/head-site:/tmp/site "${label#head:}" "$@" ;;
    *) env PYTHONPATH=/tmp/head-site:/tmp/site "$@" ;;
  esac
}
two_core() {  # $1: run name, $2: label, $3: the cores
  as "$2" timeout "${TWO_S:-150}" taskset -c "$3" python3 -m clothball.game.cli bench --load \
    --server-backend cpu --workers 1 --scene default --server-n 16 --rooms-step 2 \
    --load-max-rooms "${TWO_MAX:-20}" --load-seconds 5 --steps-past 1 --client-procs 1 --json "$OUT/$1.json" \
    2>>"$OUT/bench.err" | tail -2 >"$OUT/$1.txt"
  echo "== $1 ($2, cores $3): $(tail -1 "$OUT/$1.txt")"
}
i=0
for label in ${TWO_CORE:-}; do
  i=$((i + 1)); echo "$(uptime)"
  two_core "2core_${i}_${label%%:*}" "$label" 2,3
done
r=0
IFS=/ read -ra rounds <<<"${PAR_ROUNDS:-}"
[ ${#rounds[@]} -gt 0 ] && lscpu -e=CPU,CORE,SOCKET,NODE >"$OUT/lscpu.txt"
for round in "${rounds[@]}"; do
  r=$((r + 1)); i=0; echo "round $r: $(uptime)"
  for label in $round; do
    two_core "par_r${r}_${i}_${label%%:*}" "$label" "$((2 * i + 2)),$((2 * i + 3))" &
    i=$((i + 1))
  done
  wait
done
IFS=';' read -ra benches <<<"${BENCH:-}"
i=0
for label in ${BENCH_LABELS:-}; do
  i=$((i + 1)); j=0
  for args in "${benches[@]}"; do
    j=$((j + 1)); name="bench_${i}_${j}_${label%%:*}"
    echo "== $name ($label): bench $args"
    # shellcheck disable=SC2086  # the flags are words
    as "$label" timeout "${BENCH_S:-300}" python3 -m clothball.game.cli bench $args \
      >"$OUT/$name.txt" 2>&1
    echo "rc=$? $(grep -c . "$OUT/$name.txt") lines"
  done
done
W=${W:-16}
i=0
for label in ${HOST:-}; do
  i=$((i + 1)); name="host_${i}_${label%%:*}"
  echo "== $name ($label) $(uptime)"
  as "$label" timeout "${RUN_S:-120}" python3 -m clothball.game.cli bench --load \
    --server-backend cuda --workers "$W" --scene default --rooms-step "${STEP:-64}" \
    --load-max-rooms "${MAX:-128}" --load-seconds 5 --steps-past 1 --client-procs "${PROCS:-6}" \
    ${CPUS:-} ${EXTRA:-} --json "$OUT/$name.json" \
    2>>"$OUT/bench.err" | tail -2
done
