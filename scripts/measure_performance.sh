#!/usr/bin/env bash
# Re-measure docs/performance.md's current-state tables at this commit, from a clean clone
# (so that `make test` includes the set-up a newcomer pays). Run it on a quiet machine:
#   bash scripts/measure_performance.sh [OUT_DIR] [part ...]    parts: setup runs benches
# Each command's output goes to OUT_DIR/NAME.log, and its wall time, peak RSS and exit
# status to OUT_DIR/summary.txt. Needs ../shared beside the repository, as the tests do.
set -u
repo=$(cd "$(dirname "$0")/.." && pwd)
commit=$(git -C "$repo" rev-parse --short HEAD)
case ${1:-} in setup|runs|benches|"") out=/tmp/performance_$commit ;; *) out=$1; shift ;; esac
out=$(realpath -m "$out")
parts=${*:-setup runs benches}
mkdir -p "$out"
if [ ! -d "$out/project" ]; then
  git clone -q "$repo" "$out/project"
  ln -sfn "$(realpath "$repo/../shared")" "$out/shared"
fi
cd "$out/project"
measured=$(git rev-parse --short HEAD)
if [ "$measured" != "$commit" ]; then
  echo "$out/project holds $measured, the repository $commit: give another OUT_DIR" >&2
  exit 2
fi
py=.venv/bin/python
export PYTHONUNBUFFERED=1

measure() {  # measure NAME COMMAND...
  local name=$1; shift
  echo "$(date +%H:%M:%S) start $name: $*" >> "$out/summary.txt"
  /usr/bin/time -f "%e s wall, %M KiB max RSS" -o "$out/$name.time" timeout 900 "$@" \
    > "$out/$name.log" 2>&1
  local status=$?
  echo "$(date +%H:%M:%S) $name exit $status, $(tail -1 "$out/$name.time")" >> "$out/summary.txt"
}

{ echo "commit $commit, $(date -u)"; uptime; lscpu | grep "Model name"; } >> "$out/summary.txt"
for part in $parts; do
  case $part in
    setup)
      measure make_test make test
      measure make_demo make demo ;;
    runs|benches)
      [ -x $py ] || { echo "$out/project has no .venv: measure the setup part first" >&2; exit 2; } ;;&
    runs)
      measure smoke $py -m pipeline experiment=smoke paths.runs="$out/runs_smoke"
      measure smoke_neural $py -m pipeline experiment=smoke method=neural_btf paths.runs="$out/runs_smoke"
      measure render_smoke $py -m pipeline -m experiment=render_smoke paths.runs="$out/runs_render"
      measure brdf_map $py -m pipeline experiment=brdf_map paths.runs="$out/runs_b"
      measure fourier $py -m pipeline experiment=fourier paths.runs="$out/runs_c"
      measure typo_plus $py -m pipeline experiment=smoke +btf.crop.szie=32 paths.runs="$out/runs_typo"
      measure typo_tables $py -m pipeline.tables 'tables.experiments=[btff]' paths.runs="$out/runs_smoke"
      measure typo_cache $py -m pipeline.cache ls bogus=1
      measure typo_bench $py -m benchmarks.train bogus=1 ;;
    benches)
      measure bench $py -m benchmarks.train steps=10 threads=2 mlflow=false
      measure profile_step $py -m benchmarks.profile_step threads=1 steps=30 rounds=3
      measure ubo2014_bench $py -m benchmarks.ubo2014_load components=16
      measure render_bench $py -m benchmarks.render size=256 spp=128 crop=100 ;;
    *) echo "unknown part $part (setup, runs, benches)" >&2; exit 2 ;;
  esac
done
echo "$(date +%H:%M:%S) done; results in $out" | tee -a "$out/summary.txt"
