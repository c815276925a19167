#!/usr/bin/env bash
# Benchmark: env-steps/s through the simulator protocol (dsrl-sim-bench, a Rust client stepping random actions
# through a release dsrl-sim-worker on loopback) vs the same simulators stepped in-process in Python
# (bench/sim_reference.py: the raw env objects in a loop, and dsrl_sim's Batch called directly), at K=1 and K=16,
# side by side in one run. The protocol runs lockstep (step all K, wait, repeat) and, at K > 1, pipelined: the K
# envs in two groups, each group's next step sent while the other's is answered. Overhead = how much longer the
# protocol takes per env-step than the raw Python loop (the Batch for MetaDrive K=16, where one process cannot
# host 16 MetaDrive envs). Prints a Markdown table (also written to bench/out/sim.md, and into BENCHMARKS.md at
# SCALE=1) with the machine and whether each K = 16 row meets the goal (at most 10% overhead).
# Usage: bench/sim.sh [SCALE=1]   (SCALE multiplies the step counts)
set -euo pipefail
cd "$(dirname "$0")/.."
source bench/lib.sh
scale=${1:-1}
sim/setup.sh >&2
export PYO3_PYTHON="${PYO3_PYTHON:-$(command -v "${PYTHON:-python3}")}"
cargo build --release --locked -p dsrl-sim --bins >&2
bin=${CARGO_TARGET_DIR:-target}/release
mkdir -p bench/out
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-sim-bench.XXXXXX")
worker_pid=""
cleanup() { [ -n "$worker_pid" ] && kill "$worker_pid" 2>/dev/null; rm -rf "$work"; }
trap cleanup EXIT
"$bin/dsrl-sim-worker" --listen 127.0.0.1:0 > "$work/worker.out" 2> "$work/worker.log" &
worker_pid=$!
for _ in $(seq 600); do grep -q listening "$work/worker.out" 2>/dev/null && break; sleep 0.1; done
addr=$(sed -n 's/^dsrl-sim-worker listening on //p' "$work/worker.out")
py() { PYTHONWARNINGS=ignore .venv-sim/bin/python bench/sim_reference.py "$@" 2>/dev/null | tail -1; }
rate() { sed -n 's/.*"env_steps_per_s": \([0-9.]*\).*/\1/p'; }

out=bench/out/sim.md
{
  machine_line
  echo
  echo "| task | K | env-steps | Python, raw env loop | Python, dsrl_sim Batch | protocol, lockstep | protocol, 2 groups pipelined | overhead lockstep / pipelined |"
  echo "|---|---|---|---|---|---|---|---|"
} > "$out"
# task, K, batched steps (scaled)
while read -r task k steps; do
  steps=$((steps * scale))
  if [ "$k" -gt 1 ] && [[ "$task" == SafeMetaDrive* ]]; then
    raw="n/a (one MetaDrive env per process)"
  else
    raw=$(py --task "$task" --envs "$k" --steps "$steps" --mode raw | rate)
  fi
  batch=$(py --task "$task" --envs "$k" --steps "$steps" --mode batch | rate)
  proto=$("$bin/dsrl-sim-bench" --worker "$addr" --task "$task" --envs "$k" --steps "$steps" | rate)
  base=$raw
  [[ "$raw" == n/a* ]] && base=$batch
  overhead() { awk -v b="$base" -v p="$1" 'BEGIN { printf "%+.1f%%", (b / p - 1) * 100 }'; }
  if [ "$k" -gt 1 ]; then
    piped=$("$bin/dsrl-sim-bench" --worker "$addr" --task "$task" --envs "$k" --steps "$steps" --groups 2 | rate)
    overheads="$(overhead "$proto") / $(overhead "$piped")"
  else
    piped="n/a"
    overheads="$(overhead "$proto")"
  fi
  echo "| $task | $k | $((steps * k)) | $raw | $batch | $proto | $piped | $overheads |" | tee -a "$out" >&2
done <<'TASKS'
SafetyBallRun-v0 1 3000
SafetyBallRun-v0 16 500
SafetyHalfCheetahVelocity-v1 1 5000
SafetyHalfCheetahVelocity-v1 16 1000
SafetyPointGoal1-v0 1 2000
SafetyPointGoal1-v0 16 150
SafeMetaDrive-easymean-v0 1 600
SafeMetaDrive-easymean-v0 16 150
TASKS
# The goal, per K = 16 row: lockstep and pipelined overhead at most 10%.
python3 - "$out" >> "$out" <<'PY'
import sys
rows = [line.split("|")[1:-1] for line in open(sys.argv[1]) if line.startswith("| Safe")]
verdicts = []
for cells in rows:
    task, k, overheads = cells[0].strip(), cells[1].strip(), cells[-1].strip()
    if k != "16":
        continue
    lock, piped = (float(x.strip().rstrip("%")) for x in overheads.split("/"))
    verdicts.append("%s lockstep %s, pipelined %s" % (task, "met" if lock <= 10 else "**missed**",
                                                      "met" if piped <= 10 else "**missed**"))
print()
print("Goal (at most 10% overhead at K = 16): " + "; ".join(verdicts) + ".")
PY
cat "$out"
if [ "$scale" = 1 ]; then bench_section sim.sh "$out"; fi
