#!/usr/bin/env bash
# Benchmark: acting with a fixed policy through the simulator workers against the raw in-process Python loop, per
# core, side by side in one run (issue: data for all 38 tasks, collection speed).
#
# - Bullet and Safety-Gymnasium (OfflineBallRun-v0, OfflineHalfCheetahVelocityGymnasium-v1,
#   OfflinePointGoal1Gymnasium-v0): a saved expert (a short `dsrl-admin collect` run's expert/policy) plays
#   episodes with `dsrl-admin evaluate --workers 2 --sessions 2 --envs-per-session K`: two release workers, one
#   per core, each stepping K environments (32; 16 for PointGoal1, whose episodes are long) in two pipelined groups
#   while the policy acts on the other group. The wall time counts everything after the workers are healthy
#   (opening the sessions, that is creating the environments, included).
# - MetaDrive (OfflineMetadrive-easysparse-v0): the dataset sweep itself, `dsrl-admin collect
#   --episodes-per-setting 1` (DSRL's noisy IDM driver in the worker, 50 settings), whole process wall time, three
#   ways: a fresh session per setting (`--settings-per-session 1`, how the committed starters were built; one
#   episode per setting makes it one environment per session), blocks of 25 settings per session of one
#   environment (`--settings-per-session 25 --envs-per-session 1`), both with whole episodes driven inside the
#   worker (a `Drive` request: one round trip per episode), and blocks of 25 on 2 environments, which are stepped
#   (one round trip per step: the deal of episodes to environments depends on which finishes first).
# - Reference: `bench/sim_reference.py --mode raw`, the simulator's own env stepped in a Python loop (MetaDrive
#   with the same IDM driver steering), two processes at once, one per core; per core = the mean of the two.
#   MetaDrive has two references: the raw loop doing the same work as ours (`--mode sweep`: one env per process
#   plays half the 50 settings with the recipe's episode seeds, switching the driver on reset, timed whole with the
#   env's creation as ours is; its episodes are ours, step for step), and the raw loop stepping one setting
#   (13 km/h, factor 3.0) with creation and warm-up left out of its time.
#
# Each task runs reference and ours alternately, ROUNDS times (default 2); each round's ratio is printed.
# Prints a Markdown table (also written to bench/out/acting.md, and into BENCHMARKS.md from a run of every task at
# ROUNDS=2) with the machine and, per kind of row, whether it met the goal (80% of the raw loop in every round).
# Run it on an otherwise idle machine.
# Usage: bench/acting.sh [ROUNDS=2]
#        ONLY=REGEX bench/acting.sh   (only the tasks whose family or id matches)
set -euo pipefail
case ${1:-} in -h|--help) sed -n "2,28p" "$0"; exit 0 ;; esac
cd "$(dirname "$0")/.."
source bench/lib.sh
rounds=${1:-2}
sim/setup.sh >&2
export PYO3_PYTHON="${PYO3_PYTHON:-$(command -v "${PYTHON:-python3}")}"
echo "building the release dsrl-admin and dsrl-sim-worker" >&2
cargo build --release --locked -p dsrl-admin -p dsrl-sim --bins >&2
bin=${CARGO_TARGET_DIR:-target}/release
mkdir -p bench/out
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-acting-bench.XXXXXX")
trap 'rm -rf "$work"' EXIT
cores=2

# Two raw loops at once; prints the mean env-steps/s per process (= per core).
raw() {
  local task=$1 steps=$2 idm=${3:-}
  local extra=()
  [ -n "$idm" ] && extra=(--idm "$idm")
  for i in 1 2; do
    PYTHONWARNINGS=ignore .venv-sim/bin/python bench/sim_reference.py --task "$task" --envs 1 --steps "$steps" \
      --seed "$i" --mode raw "${extra[@]}" > "$work/raw.$i" 2>/dev/null &
  done
  wait
  python3 - "$work/raw.1" "$work/raw.2" <<'PY'
import json, sys
rates = [json.loads(open(p).read().strip().splitlines()[-1])["env_steps_per_s"] for p in sys.argv[1:]]
print(f"{sum(rates) / len(rates):.0f}")
PY
}

# The raw loop doing the MetaDrive sweep's work: two processes at once, settings 0..24 and 25..49 (one episode each,
# the recipe's seeds), each timed whole with its env's creation; prints the mean env-steps/s per process.
raw_sweep() {
  local task=$1
  PYTHONWARNINGS=ignore .venv-sim/bin/python bench/sim_reference.py --task "$task" --mode sweep --settings 0:25 \
    > "$work/raw.1" 2>/dev/null &
  PYTHONWARNINGS=ignore .venv-sim/bin/python bench/sim_reference.py --task "$task" --mode sweep --settings 25:50 \
    > "$work/raw.2" 2>/dev/null &
  wait
  python3 - "$work/raw.1" "$work/raw.2" <<'PY'
import json, sys
rates = [json.loads(open(p).read().strip().splitlines()[-1])["env_steps_per_s"] for p in sys.argv[1:]]
print(f"{sum(rates) / len(rates):.0f}")
PY
}
# A saved expert for the task: a short training run (its quality does not matter to acting speed).
expert() {
  local task=$1
  echo "training a short expert for $task" >&2
  RUST_BACKTRACE=0 "$bin/dsrl-admin" collect --task "$task" --state "$work/$task" --workers 2 --json \
    --budget-steps 20000 > /dev/null 2> "$work/$task.collect.log"
  echo "$work/$task/expert/policy"
}

# Ours with a saved expert; prints env-steps/s per core.
ours_expert() {
  local policy=$1 episodes=$2 envs=$3
  RUST_BACKTRACE=0 "$bin/dsrl-admin" evaluate "$policy" --episodes "$episodes" --workers "$cores" --sessions "$cores" \
    --envs-per-session "$envs" --json > "$work/eval.json" 2> "$work/eval.log"
  python3 - "$work/eval.json" "$cores" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
episodes = r["episodes"] if "episodes" in r else r["thresholds"][0]["episodes"]
steps = sum(e["length"] for e in episodes)
print(f"{steps / r['wall_seconds'] / int(sys.argv[2]):.0f} {steps}")
PY
}

# Ours, the MetaDrive IDM sweep with BLOCK settings per session of ENVS environments; prints env-steps/s per core.
ours_sweep() {
  local task=$1 block=$2 envs=$3 state
  state="$work/sweep.$RANDOM"
  local start end
  start=$(date +%s.%N)
  RUST_BACKTRACE=0 "$bin/dsrl-admin" collect --task "$task" --state "$state" --workers "$cores" --json \
    --episodes-per-setting 1 --settings-per-session "$block" \
    --envs-per-session "$envs" > "$work/sweep.json" 2> "$work/sweep.log"
  end=$(date +%s.%N)
  python3 - "$work/sweep.json" "$start" "$end" "$cores" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))["provenance"]["details"]
wall = float(sys.argv[3]) - float(sys.argv[2])
print(f"{d['transitions'] / wall / int(sys.argv[4]):.0f} {d['transitions']}")
PY
  rm -rf "$state"
}

out=bench/out/acting.md
{
  machine_line
  echo
  echo "| family | task | acting | round | env-steps (ours) | raw Python loop, env-steps/s per core | ours, env-steps/s per core | ours / raw |"
  echo "|---|---|---|---|---|---|---|---|"
} > "$out"
row() { awk -v r="$5" -v o="$6" -v a="$1" -v b="$2" -v c="$3" -v d="$4" -v n="$7" \
  'BEGIN { printf "| %s | %s | %s | %s | %s | %.0f | %.0f | %.0f%% |\n", a, b, c, d, n, r, o, 100 * o / r }' >> "$out"; }

# family, offline task, simulator id, raw steps per process, episodes for ours, environments per session
while read -r family task sim steps episodes envs; do
  policy=$(expert "$task")
  for round in $(seq "$rounds"); do
    echo "$task round $round: raw loop, then the saved expert through the workers" >&2
    r=$(raw "$sim" "$steps")
    read -r o n < <(ours_expert "$policy" "$episodes" "$envs")
    row "$family" "$task" "saved expert (PPO-Lagrangian actor), $envs envs per worker" "$round" "$r" "$o" "$n"
  done
done < <(grep -E "${ONLY:-.}" <<'EOF_TASKS'
bullet OfflineBallRun-v0 SafetyBallRun-v0 60000 1600 32
safety-gymnasium OfflineHalfCheetahVelocityGymnasium-v1 SafetyHalfCheetahVelocity-v1 200000 192 32
safety-gymnasium OfflinePointGoal1Gymnasium-v0 SafetyPointGoal1-v0 20000 64 16
EOF_TASKS
)

grep -qE "${ONLY:-.}" <<< "metadrive OfflineMetadrive-easysparse-v0" && for round in $(seq "$rounds"); do
  echo "OfflineMetadrive-easysparse-v0 round $round: the raw loop playing the sweep, the raw loop at one setting," \
    "then ours (a fresh session per setting, then blocks of 25 settings on 1 environment, driven, and on 2," \
    "stepped)" >&2
  rs=$(raw_sweep SafeMetaDrive-easysparse-v0)
  r=$(raw SafeMetaDrive-easysparse-v0 2000 13,3.0)
  for layout in "1 4 driven" "25 1 driven" "25 2 stepped"; do
    read -r block envs how <<< "$layout"
    read -r o n < <(ours_sweep OfflineMetadrive-easysparse-v0 "$block" "$envs")
    what="noisy IDM driver (the dataset sweep, 50 settings, $block per session, $envs env(s) each, episodes $how)"
    row metadrive OfflineMetadrive-easysparse-v0 "$what against the raw loop playing the same sweep" \
      "$round" "$rs" "$o" "$n"
    if [ "$block" = 25 ] && [ "$envs" = 1 ]; then
      row metadrive OfflineMetadrive-easysparse-v0 "$what against the raw loop at one setting, stepping only" \
        "$round" "$r" "$o" "$n"
    fi
  done
done

# The goal, per kind of row (task and acting): ours at >= 80% of the raw loop per core, in every round.
python3 - "$out" >> "$out" <<'PY'
import sys
worst = {}
for line in open(sys.argv[1]):
    cells = [c.strip() for c in line.split("|")[1:-1]]
    if len(cells) == 8 and cells[-1].endswith("%"):
        key = (cells[1], cells[2])
        worst[key] = min(worst.get(key, 1e9), float(cells[-1].rstrip("%")))
print()
print("Goal (ours at >= 80% of the raw loop per core, in every round):")
for (task, acting), w in worst.items():
    print(f"- {task}, {acting}: {'met' if w >= 80 else '**missed**'} (lowest round {w:.0f}%)")
PY
cat "$out"
if [ "$rounds" = 2 ] && [ -z "${ONLY:-}" ]; then bench_section acting.sh "$out"; fi
