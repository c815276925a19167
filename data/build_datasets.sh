#!/usr/bin/env bash
# Builds the hosted datasets of the given tasks (default: every task without a committed starter) one after another
# with `dsrl-admin collect`, each in its own state folder under ${DSRL_COLLECT_DIR:-~/.dsrl/collect}/<task>, with
# its log in <that folder>/../logs/<task>.log. Every run resumes where it stopped, so this script can be killed and
# started again at any time; a task whose output file exists is skipped.
#
# Budgets: expert recipes train for their recipe's budget_steps (BUDGET_STEPS overrides for all); MetaDrive sweeps
# play EPISODES_PER_SETTING (default 2) episodes per (acceleration, speed) setting of the paper's 50, so 100
# trajectories instead of the paper's 1000 (data/README.md says so beside the paper's numbers).
#
#   data/build_datasets.sh                         # every task without a starter
#   data/build_datasets.sh OfflineCarGoal1Gymnasium-v0 OfflineMetadrive-hardmean-v0
set -euo pipefail
cd "$(dirname "$0")/.."
root=${DSRL_COLLECT_DIR:-$HOME/.dsrl/collect}
admin=${DSRL_ADMIN:-$(command -v dsrl-admin || echo "${CARGO_TARGET_DIR:-target}/release/dsrl-admin")}
workers=${WORKERS:-2}
mkdir -p "$root/logs"
export DSRL_LOG=${DSRL_LOG:-info}
if [ $# -gt 0 ]; then
  tasks=("$@")
else
  mapfile -t tasks < <(tail -n +2 data/tasks.csv | cut -d, -f1 | while read -r t; do
    [ -d "data/starter/$t" ] || echo "$t"
  done)
fi
echo "building ${#tasks[@]} datasets with $admin ($workers workers); state under $root" >&2
for task in "${tasks[@]}"; do
  state="$root/$task"
  if compgen -G "$state/*.parquet" > /dev/null; then
    echo "$task: done ($(ls "$state"/*.parquet | head -1))" >&2
    continue
  fi
  args=(collect --task "$task" --state "$state" --workers "$workers" --json)
  case "$task" in
    OfflineMetadrive-*) args+=(--episodes-per-setting "${EPISODES_PER_SETTING:-2}") ;;
    *) [ -n "${BUDGET_STEPS:-}" ] && args+=(--budget-steps "$BUDGET_STEPS") ;;
  esac
  echo "$task: $(date -u +%FT%TZ) started: $admin ${args[*]}" >&2
  started=$(date +%s)
  if "$admin" "${args[@]}" > "$root/logs/$task.json" 2> "$root/logs/$task.log"; then
    echo "$task: finished in $(( $(date +%s) - started )) s" >&2
  else
    echo "$task: FAILED after $(( $(date +%s) - started )) s; see $root/logs/$task.log" >&2
  fi
done
