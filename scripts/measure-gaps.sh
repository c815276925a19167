#!/usr/bin/env bash
# Measures what each unbuilt full build would cost, so that every task without a committed full build has a gap with
# numbers (data/full_build_gaps.csv: the CPU seconds per step or episode, and the core-hours the rest takes). For each
# task of the plan that has no committed full build and no measured cost yet, it runs a trial of the task's build: the
# same recipe, plan and code (`dsrl-admin build`) in a state folder of its own, with the expert saving (and so logging)
# every 2 collects instead of every 20, until it has used MIN_CPU_SECONDS of CPU, stopped just after a save (an expert's
# every 2 collects, a MetaDrive sweep's every setting of 20 episodes), or MAX_MINUTES have passed. It then stops the
# trial and writes the task's record, `data/full/<task>.progress.json`: not started, with the trial's CPU seconds per
# unit and the core-hours the whole build takes at that cost (a task with a committed partial build keeps its record and
# gains the cost). At the end it regenerates the documents (`dsrl-admin docs`). The trial's state is not kept as the
# build's: `dsrl-admin build` starts the task afresh.
#
# The CPU cost comes from the process tree's CPU time, which does not depend on what else the machine runs, so the
# trials run at the lowest priority beside other work (a session of their own, nice 19). It includes the start of
# the trial's simulator workers and the expert's first update: a small share of a trial of MIN_CPU_SECONDS (300 by
# default), whatever the task costs a step, but a large one of a short trial, whose CPU per unit would be too high.
#
#   scripts/measure-gaps.sh                                   # every unbuilt task without a measured cost
#   scripts/measure-gaps.sh OfflinePointPush1Gymnasium-v0     # these tasks (measured again)
#   MIN_CPU_SECONDS=900 MAX_MINUTES=30 scripts/measure-gaps.sh  # longer trials
#
# A task whose recipe warm-starts from another build (PointPush2 from PointPush1) is measured only once that build is
# finished in the builds' root: its trial starts from it, as the real build would. Before, it is left unmeasured.
#
# Trials' state: ${DSRL_FULL_ROOT:-~/.dsrl/full}/trials/<task>/; log: <root>/measure.log.
set -euo pipefail
cd "$(dirname "$0")/.."
root=${DSRL_FULL_ROOT:-$HOME/.dsrl/full}
trials=$root/trials
admin=${DSRL_ADMIN:-$(command -v dsrl-admin || echo "${CARGO_TARGET_DIR:-target}/release/dsrl-admin")}
min_cpu_seconds=${MIN_CPU_SECONDS:-300}
max_minutes=${MAX_MINUTES:-15}
[ -x "$admin" ] || { echo "no dsrl-admin at $admin: run scripts/serve.sh (or cargo build --release) first" >&2; exit 1; }
for n in "$min_cpu_seconds" "$max_minutes"; do
  [[ $n =~ ^[1-9][0-9]*$ ]] ||
    { echo "MIN_CPU_SECONDS and MAX_MINUTES must be positive integers" >&2; exit 2; }
done
mkdir -p "$trials"

# The trials' plan: the committed one with every expert saving every 2 collects.
plan=$trials/full_builds.toml
python3 - data/full_builds.toml data/recipes "$plan" <<'EOF'
import os, re, sys
source, recipes, out = sys.argv[1:]
lines, task = [], None
for line in open(source).read().splitlines():
    if re.match(r"expert\.checkpoint_every_collects\s*=", line):
        continue
    lines.append(line)
    header = re.match(r"\[(Offline[^\]]+)\]$", line)
    if header:
        task = header.group(1)
        with open(os.path.join(recipes, task + ".toml")) as f:
            if re.search(r"^\[expert\]", f.read(), re.M):
                lines.append("expert.checkpoint_every_collects = 2")
open(out, "w").write("\n".join(lines) + "\n")
EOF

# The tasks: those named, or every task of the plan without a committed record or a measured cost.
if [ $# -gt 0 ]; then
  tasks=("$@")
  "$admin" build --plan "$plan" --root "$trials" --status "${tasks[@]}" > /dev/null  # an unknown task fails here
else
  mapfile -t tasks < <("$admin" build --plan "$plan" --root "$trials" --status --json | python3 -c '
import json, os, sys
for p in json.load(sys.stdin):
    task = p["task"]
    if os.path.exists(f"data/full/{task}.json"):
        continue
    recorded = f"data/full/{task}.progress.json"
    if os.path.exists(recorded) and json.load(open(recorded)).get("cpu_seconds_per_unit") is not None:
        continue
    print(task)')
fi
echo "measuring ${#tasks[@]} task(s): ${tasks[*]:-none}" >&2

# A trial's status, as `--status --trial --json` gives it (one task): the trial's own numbers, not the committed
# records'.
status() { "$admin" build --plan "$plan" --root "$trials" --status --trial --json "$1"; }
# `--status TASK` also lists the builds TASK starts from (a warm start): the units of TASK's own.
done_units() {
  status "$1" | python3 -c '
import json, sys
p = next(p for p in json.load(sys.stdin) if p["task"] == sys.argv[1])
print(p["done"], p["unit"], int((p.get("compute") or {}).get("cpu_seconds", 0)))' "$1"
}
# The unfinished builds a task's build starts from (its warm start's chain), which a trial would have to run whole.
sources() {
  status "$1" | python3 -c '
import json, sys
print(" ".join(p["task"] for p in json.load(sys.stdin) if p["task"] != sys.argv[1] and p["state"] != "finished"))' "$1"
}

for task in "${tasks[@]}"; do
  # A warm start's source built in the builds' own root is the one the real build would start from: the trial
  # starts from it too (a link; the trial writes only into its own task's folder, and a source still unfinished
  # there is named below and not measured from).
  for source_task in $(sources "$task"); do
    if [ -d "$root/$source_task" ] && [ ! -e "$trials/$source_task" ]; then
      ln -s "$root/$source_task" "$trials/$source_task"
    fi
  done
  from=$(sources "$task")
  if [ -n "$from" ]; then
    echo "$task starts from the finished build of $from: a trial would build that whole first; not measured" |
      tee -a "$root/measure.log" >&2
    continue
  fi
  rm -rf "${trials:?}/$task"
  echo "$(date -u +%FT%TZ) $task: a trial until $min_cpu_seconds CPU s or $max_minutes min" | tee -a "$root/measure.log" >&2
  # setsid: a session (so an autogroup) of its own, whose nice is 19: the trial takes only what is left idle.
  setsid bash -c 'echo 19 > /proc/self/autogroup 2>/dev/null || true; exec nice -n 19 "$0" build --plan "$1" --root "$2" --json "$3"' \
    "$admin" "$plan" "$trials" "$task" >> "$root/measure.log" 2>&1 < /dev/null &
  pid=$!
  deadline=$((SECONDS + 60 * max_minutes)) saved=0
  while kill -0 "$pid" 2>/dev/null && [ "$SECONDS" -lt "$deadline" ]; do
    sleep 5
    read -r now _ cpu < <(done_units "$task")
    # Only just after a save: the CPU count runs on between saves, the units done do not.
    [ "$now" -gt "$saved" ] && [ "$cpu" -ge "$min_cpu_seconds" ] && break
    saved=$now
  done
  # The build and its workers stop with it (they die with their parent).
  kill -TERM -- "-$pid" 2>/dev/null || kill -TERM "$pid" 2>/dev/null || true
  wait "$pid" 2>/dev/null || true
  # The record: the trial's CPU cost, applied to what the build has left.
  "$admin" build --plan "$plan" --root "$trials" --status --trial --record "$task" 2>&1 | tee -a "$root/measure.log" >&2
done

"$admin" docs
echo "recorded: data/full/<task>.progress.json, data/full_build_gaps.csv, data/README.md" >&2
