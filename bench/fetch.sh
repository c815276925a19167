#!/usr/bin/env bash
# Benchmark: fetching one >= 200 MB dataset version over loopback, side by side in one run:
#   cp     of the stored object (warm page cache: the ceiling of the machine's memory/disk path)
#   curl   of the download URL (-o file)
#   dsrl-client fetch into an empty cache (download + sha256 verification + fsync + rename)
# then 32 concurrent dsrl-client fetches (separate caches): errors and aggregate throughput.
# Usage: bench/fetch.sh [EPISODES=150] [ROUNDS=7]   (release build; prints a Markdown table, also bench/out/fetch.md,
# and writes it into BENCHMARKS.md when run with the defaults)
set -euo pipefail
cd "$(dirname "$0")/.."
source bench/lib.sh
episodes=${1:-150}
rounds=${2:-7}
task=OfflineMetadrive-easysparse-v0
cargo build --release --locked --workspace --bins >&2
bin=${CARGO_TARGET_DIR:-target}/release
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-bench.XXXXXX")
server_pid=""
cleanup() { [ -n "$server_pid" ] && kill "$server_pid" 2>/dev/null; rm -rf "$work"; }
trap cleanup EXIT

"$bin/dsrl-make-dataset" --task "$task" --episodes "$episodes" --seed 7 "$work/data.parquet" >&2
start_server "$work" "$bin/dsrl-server" --listen 127.0.0.1:0 --data-dir "$work/server" --starter-datasets "$work/none"
export DSRL_SERVER=$url DSRL_ADMIN_TOKEN
DSRL_ADMIN_TOKEN=$(cat "$work/server/admin-token")
version=$("$bin/dsrl-client" --json admin ingest --task "$task" "$work/data.parquet" \
  | python3 -c 'import json,sys; print(json.load(sys.stdin)["version"]["version"])')
stored="$work/server/objects/datasets/$task/$version.parquet"
size=$(stat -c %s "$stored")
download="$url/v1/datasets/$task/versions/$version/download"
cat "$stored" > /dev/null   # warm page cache

now() { date +%s.%N; }
declare -A times
for round in $(seq "$rounds"); do
  rm -f "$work/cp.out"; t0=$(now); cp "$stored" "$work/cp.out"; t1=$(now)
  times[cp]+="$(echo "$t1 - $t0" | bc) "
  rm -f "$work/curl.out"; t0=$(now); curl -sf -o "$work/curl.out" "$download"; t1=$(now)
  times[curl]+="$(echo "$t1 - $t0" | bc) "
  rm -rf "$work/cache"; t0=$(now)
  DSRL_DATASET_DIR="$work/cache" "$bin/dsrl-client" fetch "$task" --version "$version" > /dev/null 2>&1
  t1=$(now)
  times[client]+="$(echo "$t1 - $t0" | bc) "
done
[ "$(sha256sum < "$work/curl.out" | cut -d' ' -f1)" = "$version" ] || { echo "curl copy differs" >&2; exit 1; }
rm -rf "$work/cache" "$work/cp.out" "$work/curl.out"

median() { tr ' ' '\n' | grep -v '^$' | sort -g | awk '{a[NR]=$1} END {print (NR%2 ? a[(NR+1)/2] : (a[NR/2]+a[NR/2+1])/2)}'; }
mbps() { echo "scale=1; $size / 1048576 / $1" | bc; }

# 32 concurrent fetches, each into its own cache (one shared cache would serialize them on its lock).
n=32
t0=$(now)
pids=()
for i in $(seq "$n"); do
  DSRL_DATASET_DIR="$work/c$i" "$bin/dsrl-client" fetch "$task" --version "$version" > /dev/null 2> "$work/c$i.err" &
  pids+=($!)
done
failures=0
for p in "${pids[@]}"; do wait "$p" || failures=$((failures + 1)); done
t1=$(now)
wall=$(printf '%.1f' "$(echo "$t1 - $t0" | bc)")
aggregate=$(echo "scale=1; $n * $size / 1048576 / $wall" | bc)

# Seconds to milliseconds' precision (bc prints .0721...).
fmt() { for x in "$@"; do printf '%.3f ' "$x"; done; }
cp_t=$(printf '%.3f' "$(echo "${times[cp]}" | median)"); curl_t=$(printf '%.3f' "$(echo "${times[curl]}" | median)")
client_t=$(printf '%.3f' "$(echo "${times[client]}" | median)")
ratio=$(printf '%.2f' "$(echo "scale=4; $curl_t / $client_t" | bc)")
mkdir -p bench/out
{
  echo "Dataset: $task, $episodes synthetic episodes, $size bytes ($(echo "scale=1; $size/1048576" | bc) MiB); $rounds rounds, median."
  machine_line
  echo
  echo "| method | median seconds | MiB/s | vs curl |"
  echo "|---|---|---|---|"
  echo "| cp of the stored file (warm cache) | $cp_t | $(mbps "$cp_t") | $(printf '%.2f' "$(echo "scale=4; $curl_t / $cp_t" | bc)")x |"
  echo "| curl -o (loopback) | $curl_t | $(mbps "$curl_t") | 1.00x |"
  echo "| dsrl-client fetch (verify + fsync + rename) | $client_t | $(mbps "$client_t") | **${ratio}x** |"
  echo
  echo "Goal (dsrl-client fetch at >= 0.8x curl's speed): $(echo "$ratio >= 0.8" | bc | sed 's/1/met/; s/0/not met/')."
  echo
  echo "$n concurrent dsrl-client fetches: **$failures errors**, ${wall} s wall, **aggregate ${aggregate} MiB/s**."
  echo
  echo "All rounds (s): cp $(fmt ${times[cp]})| curl $(fmt ${times[curl]})| client $(fmt ${times[client]})"
} > bench/out/fetch.md
cat bench/out/fetch.md
if [ "$episodes" = 150 ] && [ "$rounds" = 7 ]; then bench_section fetch.sh bench/out/fetch.md; fi
