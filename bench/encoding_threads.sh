#!/usr/bin/env bash
# Benchmark: every dataset write (ingest, filters) encodes a row group's columns on up to 4 threads (the cores)
# instead of one, the file unchanged. Side by side in one run, on a DSRL-layout HDF5 of CarPush2's shape (random
# values, bench/make_dsrl_scale.py) with EPISODES trajectories of 1,000 steps: a release dsrl-server with
# DSRL_ENCODING_THREADS=1 (every column on the writing thread, as parquet's ArrowWriter does) against the default,
# each ingesting the file and computing two uncached noise filters; the two rounds alternate the variants. Each row
# also gives the version id, which must be the same for every variant. Writes its table into BENCHMARKS.md between
# its markers. Usage: bench/encoding_threads.sh [EPISODES=1500]   (a release build; ~2 GB of disk per 1,000 episodes)
set -euo pipefail
cd "$(dirname "$0")/.."
source bench/lib.sh
episodes=${1:-1500}
task=OfflineCarPush2Gymnasium-v0
tests/golden/reference-venv.sh >&2
.venv-golden/bin/python -m pip install --quiet --disable-pip-version-check h5py >&2
cargo build --release --locked -p dsrl-server -p dsrl-client >&2
bin=${CARGO_TARGET_DIR:-target}/release
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-encoding-bench.XXXXXX")
server_pid=""
cleanup() { [ -n "$server_pid" ] && kill "$server_pid" 2>/dev/null; rm -rf "$work"; }
trap cleanup EXIT
file="$work/SafetyCarPush2Gymnasium-v0-250-$episodes.hdf5"
echo "writing $file" >&2
.venv-golden/bin/python bench/make_dsrl_scale.py "$file" "$episodes" >&2
seconds() { python3 -c "import sys; print('%.1f' % (float(sys.argv[2]) - float(sys.argv[1])))" "$1" "$2"; }
rows=()
# One variant: a fresh server with DSRL_ENCODING_THREADS=$1 ("" for the default), the ingest, two noise filters.
variant() {
  local threads=$1 round=$2 d="$work/server-$round-${1:-default}"
  mkdir -p "$d"
  DSRL_ENCODING_THREADS=$threads "$bin/dsrl-server" --listen 127.0.0.1:0 --data-dir "$d/data" \
    --starter-datasets "$d/none" > "$d/server.out" 2> "$d/server.log" &
  server_pid=$!
  for _ in $(seq 100); do grep -q listening "$d/server.out" 2>/dev/null && break; sleep 0.1; done
  local url t0 t1 version ingest noise=()
  url=$(sed -n 's/^dsrl-server listening on //p' "$d/server.out")
  export DSRL_SERVER=$url DSRL_ADMIN_TOKEN=$(cat "$d/data/admin-token") DSRL_DATASET_DIR="$d/cache"
  t0=$(date +%s.%N)
  "$bin/dsrl-client" admin ingest --task "$task" "$file" > /dev/null
  t1=$(date +%s.%N)
  ingest=$(seconds "$t0" "$t1")
  version=$(curl -sf "$url/v1/datasets/$task/versions/latest" | python3 -c 'import json,sys; print(json.load(sys.stdin)["version"])')
  for f in 0.1 0.2; do
    t0=$(date +%s.%N)
    curl -sf -o /dev/null -H "Authorization: Bearer $DSRL_ADMIN_TOKEN" \
      "$url/v1/datasets/$task/versions/$version?filter=noise%3D$f"
    t1=$(date +%s.%N)
    noise+=("$(seconds "$t0" "$t1")")
  done
  kill "$server_pid"; wait "$server_pid" 2>/dev/null || true; server_pid=""
  rm -rf "$d"
  local label="default ($(nproc) cores, at most 4)"
  [ -n "$threads" ] && label=$threads
  rows+=("| $round | $label | $ingest | ${noise[0]} | ${noise[1]} | \`${version:0:12}\` |")
}
for round in 1 2; do
  if [ "$round" = 1 ]; then variant 1 "$round"; variant "" "$round"; else variant "" "$round"; variant 1 "$round"; fi
done
table=$work/table.md
{
  echo "File: $(basename "$file"), $(( $(stat -c %s "$file") / 1048576 )) MiB, $episodes trajectories x 1000 steps."
  machine_line
  echo
  echo "| round | encoding threads | ingest (s) | noise=0.1, uncached (s) | noise=0.2, uncached (s) | version id |"
  echo "|---|---|---|---|---|---|"
  printf '%s\n' "${rows[@]}"
} > "$table"
cat "$table"
bench_section encoding_threads.sh "$table"
