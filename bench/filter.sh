#!/usr/bin/env bash
# Benchmark: DSRL's pre_process_data (arrays already in memory) vs our server answering a filter request end to end
# (read the parent version, filter, write and store the Parquet result, stream it back), uncached and cached, side
# by side in one run on one >= 300k-transition dataset (synthetic, OfflineAntRun-v0 shape, 33 features).
# Usage: bench/filter.sh [ROUNDS=3]   (release build; needs PyPI access once for .venv-golden). Prints a Markdown
# table (also bench/out/filter.md), written into BENCHMARKS.md at 3 rounds.
set -euo pipefail
cd "$(dirname "$0")/.."
source bench/lib.sh
rounds=${1:-3}
task=OfflineAntRun-v0
tests/golden/reference-venv.sh >&2
cargo build --release --locked --workspace --bins >&2
bin=${CARGO_TARGET_DIR:-target}/release
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-filter-bench.XXXXXX")
server_pid=""
cleanup() { [ -n "$server_pid" ] && kill "$server_pid" 2>/dev/null; rm -rf "$work"; }
trap cleanup EXIT
"$bin/dsrl-make-dataset" --task "$task" --episodes 1700 --seed 21 "$work/data.parquet" >&2

reference=$(.venv-golden/bin/python bench/filter_reference.py "$work/data.parquet" "$rounds" 2>/dev/null)

fresh_server() {
  rm -rf "$work/server"
  start_server "$work" "$bin/dsrl-server" --listen 127.0.0.1:0 --data-dir "$work/server" \
    --starter-datasets "$work/none"
  DSRL_ADMIN_TOKEN=$(cat "$work/server/admin-token") DSRL_SERVER=$url \
    "$bin/dsrl-client" admin ingest --task "$task" "$work/data.parquet" > /dev/null
}
stop_server() { kill "$server_pid"; wait "$server_pid" 2>/dev/null || true; server_pid=""; }
now() { date +%s.%N; }
median() { tr ' ' '\n' | grep -v '^$' | sort -g | awk '{a[NR]=$1} END {print (NR%2 ? a[(NR+1)/2] : (a[NR/2]+a[NR/2+1])/2)}'; }

filters=("density=0.5" "noise=0.05" "obs_noise=0.1" "discard=tempting" "epsilon=100")
declare -A uncached cached
for round in $(seq "$rounds"); do
  fresh_server   # a fresh server: nothing cached
  for f in "${filters[@]}"; do
    q=$(python3 -c 'import sys, urllib.parse; print(urllib.parse.quote(sys.argv[1]))' "$f")
    download="$url/v1/datasets/$task/versions/latest/download?filter=$q"
    t0=$(now); curl -sf -o /dev/null "$download"; t1=$(now)
    uncached[$f]+="$(echo "$t1 - $t0" | bc) "
    t0=$(now); curl -sf -o /dev/null "$download"; t1=$(now)
    cached[$f]+="$(echo "$t1 - $t0" | bc) "
  done
  computed=$(curl -s "$url/metrics" | sed -n 's/^dsrl_filters_total{outcome="computed"} //p')
  [ "$computed" = "${#filters[@]}" ] || { echo "expected ${#filters[@]} computations, saw $computed" >&2; exit 1; }
  stop_server
done

rows=$(echo "$reference" | python3 -c 'import json,sys; print(json.load(sys.stdin)["rows"])')
speedups=() cached_speedups=()
mkdir -p bench/out
{
  echo "Dataset: $task shape, $rows transitions, 1700 episodes (synthetic, seed 21); $rounds rounds, median seconds."
  machine_line
  echo
  echo "| filter | reference, as shipped (with its PNG) | reference, plotting stubbed | ours, uncached (read, filter, write, store, download) | speed-up vs as shipped | ours, cached (download only) |"
  echo "|---|---|---|---|---|---|"
  for f in "${filters[@]}"; do
    shipped=$(echo "$reference" | python3 -c 'import json,sys; print(round(json.load(sys.stdin)["seconds"][sys.argv[1]]["as_shipped"], 3))' "$f")
    stubbed=$(echo "$reference" | python3 -c 'import json,sys; print(round(json.load(sys.stdin)["seconds"][sys.argv[1]]["stubbed"], 3))' "$f")
    u=$(echo "${uncached[$f]}" | median); c=$(echo "${cached[$f]}" | median)
    speedups+=("$(echo "$shipped / $u" | bc -l)"); cached_speedups+=("$(echo "$shipped / $c" | bc -l)")
    printf '| %s | %.3f | %.3f | %.3f | %.2fx | %.3f |\n' "$f" "$shipped" "$stubbed" "$u" "${speedups[-1]}" "$c"
  done
  echo
  echo "Each round's uncached requests computed exactly one filtered version per filter (checked via /metrics); the"
  echo "cached requests computed none."
  echo
  python3 - "${speedups[*]}" "${cached_speedups[*]}" <<'PY'
import sys
u = [float(x) for x in sys.argv[1].split()]
c = [float(x) for x in sys.argv[2].split()]
print("Goal (uncached >= 20x faster than the reference as shipped): %s; uncached runs at %.2f-%.2fx the reference's"
      " speed, cached at %.1f-%.1fx." % ("met" if min(u) >= 20 else "**not met**", min(u), max(u), min(c), max(c)))
PY
} > bench/out/filter.md
cat bench/out/filter.md
if [ "$rounds" = 3 ]; then bench_section filter.sh bench/out/filter.md; fi
