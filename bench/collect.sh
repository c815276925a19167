#!/usr/bin/env bash
# Benchmark: dataset collection throughput per simulator family with `dsrl-admin collect` (release build, 2 local
# workers): env-steps/s and episodes/min, and for the expert recipes where the time goes per collect (waiting for
# the simulators, the policy's forward passes while acting, the PPO-Lagrangian update). Short budgets of the
# committed recipes: Bullet OfflineBallRun-v0 and OfflineAntRun-v0, Safety-Gymnasium OfflinePointGoal1Gymnasium-v0
# and OfflineCarCircle1Gymnasium-v0 (experts), MetaDrive OfflineMetadrive-easysparse-v0 (the IDM sweep,
# one episode per setting). Prints a Markdown table (also written to bench/out/collect.md, and into BENCHMARKS.md at
# SCALE=1 with every row and this build).
# *Worker idle s* is how long the workers had no request in flight, on average over the sessions (training.csv's
# worker_idle_seconds; "–" where the binary does not record it).
# Usage: bench/collect.sh [SCALE=1]   (SCALE multiplies the budgets)
#        DSRL_ADMIN=/path/to/older/dsrl-admin bench/collect.sh   (the same runs with another build, for before/after;
#        a dsrl-sim-worker must lie beside it)
#        ONLY=REGEX bench/collect.sh   (only the rows whose family or task matches)
set -euo pipefail
cd "$(dirname "$0")/.."
source bench/lib.sh
scale=${1:-1}
sim/setup.sh >&2
export PYO3_PYTHON="${PYO3_PYTHON:-$(command -v "${PYTHON:-python3}")}"
cargo build --release --locked -p dsrl-admin -p dsrl-sim --bins >&2
bin=${CARGO_TARGET_DIR:-target}/release
admin=${DSRL_ADMIN:-$bin/dsrl-admin}
mkdir -p bench/out
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-collect-bench.XXXXXX")
trap 'rm -rf "$work"' EXIT

out=bench/out/collect.md
{
  machine_line
  echo
  echo "| family | task | method | env-steps | episodes | wall s | env-steps/s | episodes/min | simulator s | acting s | update s | worker idle s | update per collect (ms) |"
  echo "|---|---|---|---|---|---|---|---|---|---|---|---|---|"
} > "$out"
# family, task, budget flag, budget (scaled)
while read -r family task flag budget; do
  [ "$flag" = "--budget-steps" ] && budget=$((budget * scale))
  start=$(date +%s.%N)
  RUST_BACKTRACE=0 "$admin" collect --task "$task" --state "$work/$task" --workers 2 --json "$flag" "$budget" \
    > "$work/$task.json" 2> "$work/$task.log"
  wall=$(echo "$(date +%s.%N) - $start" | bc)
  python3 - "$family" "$task" "$wall" "$work/$task.json" "$work/$task" >> "$out" <<'PY'
import json, sys, csv, os
family, task, wall, report, state = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4], sys.argv[5]
d = json.load(open(report))["provenance"]["details"]
log = os.path.join(state, "expert", "training.csv")
if os.path.exists(log):
    rows = list(csv.DictReader(open(log)))
    steps = int(rows[-1]["steps"])
    episodes = d["episodes_collected"]
    sim, act, upd = (sum(float(r[k]) for r in rows) for k in ("simulator_seconds", "acting_seconds", "update_seconds"))
    idle = f"{sum(float(r['worker_idle_seconds']) for r in rows):.1f}" if "worker_idle_seconds" in rows[0] else "–"
    method, per = "PPO-Lagrangian expert", f"{1000 * upd / len(rows):.0f}"
    extra = f"{sim:.1f} | {act:.1f} | {upd:.1f} | {idle} | {per}"
else:
    # The sweep keeps every episode here (50 < buffer capacity; the final grid drops only costs above the cap).
    steps, episodes = d["transitions"], d["episodes_collected"]
    method, extra = "noisy-IDM sweep", "– | – | – | – | –"
print(f"| {family} | {task} | {method} | {steps:,} | {episodes:,} | {wall:.0f} | {steps / wall:,.0f} | {60 * episodes / wall:,.0f} | {extra} |")
PY
done < <(grep -E "${ONLY:-.}" <<'EOF_TASKS'
bullet OfflineBallRun-v0 --budget-steps 100000
bullet OfflineAntRun-v0 --budget-steps 50000
safety-gymnasium OfflinePointGoal1Gymnasium-v0 --budget-steps 50000
safety-gymnasium OfflineCarCircle1Gymnasium-v0 --budget-steps 50000
metadrive OfflineMetadrive-easysparse-v0 --episodes-per-setting 1
EOF_TASKS
)
cat "$out"
if [ "$scale" = 1 ] && [ -z "${ONLY:-}" ] && [ -z "${DSRL_ADMIN:-}" ]; then bench_section collect.sh "$out"; fi
