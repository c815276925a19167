#!/usr/bin/env bash
# Benchmark at the paper's largest size (issue: datasets at the paper's size): a DSRL-layout HDF5 of CarPush2's shape
# at the paper's count (4,407 trajectories x 1,000 steps, 88 features; random values, ~3 GB), hosted by a release
# dsrl-server with no simulator workers, beside DSRL 0.1.0's own get_dataset(h5path) + pre_process_data on the same
# file. For each step: wall seconds and the server's peak resident memory during it (sampled every 0.1 s from
# /proc; the reference: its own peak). Prints a Markdown table for BENCHMARKS.md with the command, machine and date.
# Usage: bench/scale.sh [EPISODES=4407]   (needs ~25 GB of free disk in $TMPDIR; PyPI once for .venv-golden)
set -euo pipefail
cd "$(dirname "$0")/.."
source bench/lib.sh
episodes=${1:-4407}
task=OfflineCarPush2Gymnasium-v0
tests/golden/reference-venv.sh >&2
.venv-golden/bin/python -m pip install --quiet --disable-pip-version-check h5py >&2
cargo build --release --locked --workspace --bins >&2
bin=${CARGO_TARGET_DIR:-target}/release
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-scale-bench.XXXXXX")
server_pid=""
cleanup() { [ -n "$server_pid" ] && kill "$server_pid" 2>/dev/null; rm -rf "$work"; }
trap cleanup EXIT
file="$work/SafetyCarPush2Gymnasium-v0-250-$episodes.hdf5"
echo "writing $file" >&2
.venv-golden/bin/python bench/make_dsrl_scale.py "$file" "$episodes"
size=$(stat -c %s "$file")

start_server "$work" "$bin/dsrl-server" --listen 127.0.0.1:0 --data-dir "$work/server" --starter-datasets "$work/none"
export DSRL_SERVER=$url DSRL_ADMIN_TOKEN=$(cat "$work/server/admin-token") DSRL_DATASET_DIR="$work/cache"

# Runs "$@" while sampling the server's resident memory; prints "seconds peak_bytes". The disk is flushed first
# (untimed), so a step is not charged for the write-back of the gigabytes the step before it wrote.
measure() {
  local peak=0 rss t0 t1 pid
  sync
  t0=$(date +%s.%N)
  "$@" > /dev/null &
  pid=$!
  while kill -0 "$pid" 2>/dev/null; do
    rss=$(awk '/^VmRSS/ {print $2 * 1024}' "/proc/$server_pid/status")
    [ "$rss" -gt "$peak" ] && peak=$rss
    sleep 0.1
  done
  wait "$pid"
  t1=$(date +%s.%N)
  echo "$(echo "$t1 - $t0" | bc) $peak"
}
rows=()
row() { rows+=("| $1 | $(printf '%.1f' "$2") | $(( $3 / 1048576 )) MiB | $4 |"); }
read -r s p < <(measure "$bin/dsrl-client" admin ingest --task "$task" "$file"); row "ingest (HDF5 upload)" "$s" "$p" "–"
version=$(curl -sf "$url/v1/datasets/$task/versions/latest" | python3 -c 'import json,sys; print(json.load(sys.stdin)["version"])')
read -r s p < <(measure "$bin/dsrl-client" fetch "$task"); row "fetch, plain" "$s" "$p" "–"
rm -rf "$work/cache"  # each fetched copy is removed once timed: the run needs its disk for the server's objects
for f in noise=0.1 density=0.5; do
  sync
  ref=$(.venv-golden/bin/python bench/scale_reference.py "$file" "$f")
  ref_s=$(echo "$ref" | python3 -c 'import json,sys; d=json.load(sys.stdin); print("%.1f s (load %.1f + filter %.1f), %d MiB" % (d["seconds"], d["load_seconds"], d["filter_seconds"], d["peak_rss_bytes"] // 1048576))')
  read -r s p < <(measure "$bin/dsrl-client" fetch "$task" --filter "$f"); row "fetch --filter $f, uncached" "$s" "$p" "$ref_s"
  rm -rf "$work/cache"
  read -r s p < <(measure "$bin/dsrl-client" fetch "$task" --filter "$f"); row "fetch --filter $f, cached on the server" "$s" "$p" "–"
  rm -rf "$work/cache"
  if [ "$f" = noise=0.1 ]; then
    # The same plain fetch again, right after the cached filtered one of the same size: the two compare in the same
    # state of the page cache, which the reference's load (gigabytes of its own) and the filters have changed since
    # the first plain fetch.
    read -r s p < <(measure "$bin/dsrl-client" fetch "$task"); row "fetch, plain, again (beside the cached filtered fetch)" "$s" "$p" "–"
    rm -rf "$work/cache"
  fi
done
# Four distinct uncached filters asked for at once (two compute at a time, datasets.max_concurrent_derivations).
concurrent() {
  local f
  for f in noise%3D0.02 noise%3D0.03 density%3D0.25 noise%3D0.04; do
    curl -sf -o /dev/null -H "Authorization: Bearer $DSRL_ADMIN_TOKEN" \
      "$url/v1/datasets/$task/versions/$version?filter=$f" &
  done
  wait
}
read -r s p < <(measure concurrent); row "4 distinct uncached filters at once (manifests)" "$s" "$p" "–"
rm -rf "$work/cache"
read -r s p < <(measure curl -sf -o "$work/export.hdf5" "$url/v1/datasets/$task/versions/$version/download?format=hdf5")
export_bytes=$(stat -c %s "$work/export.hdf5")
rm -f "$work/export.hdf5"
row "HDF5 export, first request ($(( export_bytes / 1048576 )) MiB: $(echo "$export_bytes / $s / 1048576" | bc) MiB/s)" "$s" "$p" "–"
read -r s p < <(measure "$bin/dsrl-client" fetch "$task" --format hdf5); row "fetch --format hdf5 (the stored export)" "$s" "$p" "–"

table=$work/table.md
{
  echo "File: $(basename "$file"), $(( size / 1048576 )) MiB, $episodes trajectories x 1000 steps, 88 observation features."
  machine_line
  echo
  echo "| step | ours: wall s | ours: server peak RSS | DSRL 0.1.0 on the same file |"
  echo "|---|---|---|---|"
  printf '%s\n' "${rows[@]}"
} > "$table"
cat "$table"
# The table goes into BENCHMARKS.md between its markers (only from a run at the paper's count).
if [ "$episodes" = 4407 ]; then
  bench_section scale.sh "$table"
fi
