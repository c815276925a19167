#!/usr/bin/env bash
# Cuts the committed starter of a task from its finished build (state folder from data/build_datasets.sh): the
# build's episodes thinned to at most N (default 100) spread over the (reward, cost) plane by the trajectory
# buffer's seeded grid thinning, written in the compact form (`dsrl-admin collect --compact`). A starter file must
# stay within 8 MB: when the cut (or its largest part) is larger, N is lowered in proportion and the cut is made
# again in a scratch folder, so only the final files reach data/starter/<task>. Nothing is simulated again.
# `--parts K` writes the cut as K files of whole episodes (`<name>.part-I-of-K.parquet`, each within 8 MB), which
# the server joins back into one version: for 1000-step tasks whose 50 trajectories do not fit one file.
#
#   data/cut_starter.sh OfflineCarGoal1Gymnasium-v0 [N] [extra dsrl-admin collect flags, e.g. --parts 2]
set -euo pipefail
cd "$(dirname "$0")/.."
task=$1
n=${2:-100}
shift $(( $# >= 2 ? 2 : 1 ))
root=${DSRL_COLLECT_DIR:-$HOME/.dsrl/collect}
admin=${DSRL_ADMIN:-$(command -v dsrl-admin || echo "${CARGO_TARGET_DIR:-target}/release/dsrl-admin")}
limit=$((8 * 1000 * 1000 - 200 * 1000))
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT
while :; do
  rm -rf "${scratch:?}"/*
  echo "$task: cutting $n episodes" >&2
  "$admin" collect --task "$task" --state "$root/$task" --max-episodes "$n" --compact --out "$scratch" --json "$@" \
    > "$scratch/report.json"
  size=$(stat -c %s "$scratch"/*.parquet | sort -n | tail -1)
  if [ "$size" -le "$limit" ]; then
    break
  fi
  n=$(( n * limit / size * 95 / 100 ))
  echo "$task: a file of $size bytes is over the budget; trying $n episodes" >&2
done
mkdir -p "data/starter/$task"
rm -f "data/starter/$task"/*
mv "$scratch"/*.parquet "$scratch"/*.provenance.json "data/starter/$task/"
for file in "data/starter/$task"/*.parquet; do
  echo "$task: $(basename "$file") ($(stat -c %s "$file") bytes)" >&2
done
echo "$task: version $(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["version"])' "$scratch/report.json")" >&2
