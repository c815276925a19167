#!/usr/bin/env bash
# Measures what each unbuilt full build would cost, so that every task without a committed full build has a gap
# with numbers (data/full_build_gaps.csv: the rate, and the core-hours the rest would take). For each task of the
# plan that has no committed full build and has not been measured yet, it starts the task's real build
# (`dsrl-admin build`, resumable: this is the first part of that build, not a separate probe), lets it run until its
# state shows at least MIN_STEPS environment steps (expert recipes) or MIN_EPISODES episodes (MetaDrive's IDM
# sweeps), or MAX_MINUTES have passed, stops it, and at the end records every unfinished task's numbers with
# `dsrl-admin build --status --record` and regenerates the documents (`dsrl-admin docs`).
#
# The CPU per unit comes from the build's process-tree CPU time, which does not depend on what else the machine
# runs, so this may run at the lowest priority beside other work (it does: a session of its own, nice 19); the wall
# rate it also records does depend on that.
#
#   scripts/measure-gaps.sh                                   # every unbuilt task not measured yet
#   scripts/measure-gaps.sh OfflinePointPush1Gymnasium-v0     # these tasks (measured again)
#   MIN_STEPS=60000 MAX_MINUTES=30 scripts/measure-gaps.sh    # longer measurements
#
# State: ${DSRL_FULL_ROOT:-~/.dsrl/full}/<task>/ (a later `dsrl-admin build TASK` continues from it); log:
# <root>/measure.log. Run it from the repository root's scripts folder's parent (it cds there itself).
set -euo pipefail
cd "$(dirname "$0")/.."
root=${DSRL_FULL_ROOT:-$HOME/.dsrl/full}
admin=${DSRL_ADMIN:-$(command -v dsrl-admin || echo "${CARGO_TARGET_DIR:-target}/release/dsrl-admin")}
min_steps=${MIN_STEPS:-40000}
min_episodes=${MIN_EPISODES:-20}
max_minutes=${MAX_MINUTES:-20}
[ -x "$admin" ] || { echo "no dsrl-admin at $admin: run scripts/serve.sh (or cargo build --release) first" >&2; exit 1; }
for n in "$min_steps" "$min_episodes" "$max_minutes"; do
  [[ $n =~ ^[1-9][0-9]*$ ]] || { echo "MIN_STEPS, MIN_EPISODES and MAX_MINUTES must be positive integers" >&2; exit 2; }
done
mkdir -p "$root"

# The tasks: those named, or every task of the plan without a committed record or a committed measurement.
if [ $# -gt 0 ]; then
  tasks=("$@")
  "$admin" build --root "$root" --status "${tasks[@]}" > /dev/null  # fails on an unknown task, before any work
else
  mapfile -t tasks < <("$admin" build --root "$root" --status --json | python3 -c '
import json, os, sys
for p in json.load(sys.stdin):
    task = p["task"]
    if os.path.exists(f"data/full/{task}.json") or p["state"] == "finished":
        continue
    recorded = f"data/full/{task}.progress.json"
    if os.path.exists(recorded) and json.load(open(recorded)).get("remaining_core_hours") is not None:
        continue
    print(task)')
fi
echo "measuring ${#tasks[@]} task(s): ${tasks[*]:-none}" >&2

# Units done so far by one task's build, from `--status --json`.
done_units() {
  "$admin" build --root "$root" --status --json "$1" | python3 -c '
import json, sys
p = json.load(sys.stdin)[0]
print(p["done"], p["unit"])'
}

for task in "${tasks[@]}"; do
  read -r start unit < <(done_units "$task")
  [ "$unit" = steps ] && goal=$((start + min_steps)) || goal=$((start + min_episodes))
  echo "$(date -u +%FT%TZ) $task: building from $start $unit until $goal $unit or $max_minutes min" | tee -a "$root/measure.log" >&2
  # setsid: a session (so an autogroup) of its own, whose nice is 19: the build takes only what is left idle.
  setsid bash -c 'echo 19 > /proc/self/autogroup 2>/dev/null || true; exec nice -n 19 "$0" build --root "$1" --json "$2"' \
    "$admin" "$root" "$task" >> "$root/measure.log" 2>&1 < /dev/null &
  pid=$!
  deadline=$((SECONDS + 60 * max_minutes))
  while kill -0 "$pid" 2>/dev/null && [ "$SECONDS" -lt "$deadline" ]; do
    sleep 20
    read -r now _ < <(done_units "$task")
    [ "$now" -ge "$goal" ] && break
  done
  # The build and its workers stop with it (they die with their parent); the state folder keeps what was done.
  kill -TERM -- "-$pid" 2>/dev/null || kill -TERM "$pid" 2>/dev/null || true
  wait "$pid" 2>/dev/null || true
  read -r now _ < <(done_units "$task")
  echo "$(date -u +%FT%TZ) $task: stopped at $now $unit" | tee -a "$root/measure.log" >&2
done

[ ${#tasks[@]} -eq 0 ] || "$admin" build --root "$root" --status --record "${tasks[@]}"
"$admin" docs
echo "recorded: data/full/<task>.progress.json, data/full_build_gaps.csv, data/README.md" >&2
