#!/usr/bin/env bash
# The leaderboard's reference entries: BC-All and BC-Safe (spec 5.5: MLP [256, 256], lr 1e-3, batch 512; BC-Safe
# one model per cost threshold on the episodes whose cost return is at most it) trained in candle by dsrl-train on
# each task's hosted dataset (fetched from the server, `latest`) and submitted to that server's leaderboard.
# Needs DSRL_SERVER and a user token in DSRL_TOKEN (an admin: `dsrl-client admin create-user reference`).
# Usage: data/reference_entries.sh [--steps N (default 100000, OSRL's)] [--seed S] TASK...
#   e.g. data/reference_entries.sh --steps 10000 OfflineBallRun-v0 OfflineCarRun-v0
set -euo pipefail
steps=100000 seed=0 tasks=()
while [ $# -gt 0 ]; do
  case $1 in
    --steps) steps=$2; shift 2 ;;
    --seed) seed=$2; shift 2 ;;
    -h|--help) sed -n '2,8p' "$0"; exit 0 ;;
    *) tasks+=("$1"); shift ;;
  esac
done
[ ${#tasks[@]} -gt 0 ] || { echo "name at least one task" >&2; exit 2; }
: "${DSRL_SERVER:?set DSRL_SERVER}" "${DSRL_TOKEN:?set DSRL_TOKEN to a user token}"
train=${DSRL_TRAIN:-dsrl-train}
out=${OUT:-policies}
for task in "${tasks[@]}"; do
  for mode in all safe; do
    name=$([ $mode = all ] && echo BC-All || echo BC-Safe)
    "$train" bc --task "$task" --mode $mode --server "$DSRL_SERVER" --steps "$steps" --seed "$seed" \
      --out "$out/$task" --submit "$name"
  done
done
