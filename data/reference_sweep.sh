#!/usr/bin/env bash
# The committed reference results (data/reference/results.jsonl) as one command: the runs of
# data/reference_entries.sh that produced them, in the order they were run. Each phase adds its entries to the
# results file when its scoring is done; the whole sweep resumes where it stopped (state in ~/.dsrl/reference).
# Budgets, as fractions of OSRL's (data/reference/README.md has every cell's compute):
#   1. BC-All and BC-Safe on all 38 tasks at 1/10 of OSRL's steps (10,000; MetaDrive 20,000 of 200,000), seed 0.
#   2. CDT, BCQ-Lag, BEAR-Lag, CPQ, COptiDICE and CAPS on six tasks (4 Bullet, 1 Safety-Gymnasium, 1 MetaDrive),
#      seed 0: BCQ-Lag 2,000 steps per threshold, BEAR-Lag 6,000, CPQ and COptiDICE 5,000 (1/20), CDT 600 at batch
#      512, CAPS 2,000 (BallRun 20,000); batch 512 throughout (OSRL's, but CDT's 2048).
#   3. Training seeds 1 and 2 of all eight on BallRun and CarCircle, at the same budgets.
#   4. FISOR and LSPC (beyond the paper) on the six tasks, seed 0, at what this machine allows: FISOR 500 steps at
#      its batch 2048 (1/2000 of its code's 1,000,000), LSPC 2,000 at its 1024 (1/500); the Bullet four first.
#   1r. Phase 1 trained again from scratch (--reproduce): its entries take the commit of this dsrl-train where the
#      checkpoints come out as scored. Phase 1 was trained by a build with uncommitted learner sources.
# Usage: data/reference_sweep.sh [--jobs J] [--phases "1 2 3"]   (J models trained at once, one core each; 2)
#   In the background beside other work: setsid nohup nice -n 19 data/reference_sweep.sh ... &. Started as its own
#   session's leader, it also lowers its session's scheduling group (Linux autogroup, where `nice` ranks processes
#   only within their session: a sweep at nice 19 in its own session would otherwise get an equal share).
set -euo pipefail
cd "$(dirname "$0")/.."
jobs=2 phases="1 2 3"
while [ $# -gt 0 ]; do
  case $1 in
    --jobs) jobs=$2; shift 2 ;;
    --phases) phases=$2; shift 2 ;;
    -h|--help) sed -n '2,18p' "$0"; exit 0 ;;
    *) echo "unknown argument $1" >&2; exit 2 ;;
  esac
done
if [ "$(ps -o sid= -p $$ | tr -d ' ')" = "$$" ] && [ -w /proc/self/autogroup ]; then
  echo 19 > /proc/self/autogroup 2> /dev/null || true
fi
run() { data/reference_entries.sh --jobs "$jobs" --evaluators 2 "$@"; }
metadrive=()
others=()
for task in $(awk -F, 'NR > 1 { print $1 }' data/tasks.csv); do
  case $task in OfflineMetadrive-*) metadrive+=("$task") ;; *) others+=("$task") ;; esac
done
# Those of the given tasks that have an entry in the results file naming a build with uncommitted sources.
modified() {
  python3 - data/reference/results.jsonl "$@" <<'EOF'
import json, sys
entries = [json.loads(line) for line in open(sys.argv[1])]
unmade = {e["task"] for e in entries if e["code_commit"].endswith("-modified")}
sys.stdout.writelines(f"{t}\n" for t in sys.argv[2:] if t in unmade)
EOF
}
six=(OfflineBallRun-v0 OfflineCarRun-v0 OfflineBallCircle-v0 OfflineCarCircle-v0 OfflinePointGoal1Gymnasium-v0
     OfflineMetadrive-easysparse-v0)
offline=(--batch-size 512 --steps 2000 --bearl-steps 6000 --steps-for cpq=5000 --steps-for coptidice=5000
         --cdt-steps 600 --caps-steps 2000)
for phase in $phases; do
  echo "$(date -u +%FT%TZ) reference sweep: phase $phase" >&2
  case $phase in
    1)
      run --methods "bc-all bc-safe" --steps 10000 "${others[@]}"
      run --methods "bc-all bc-safe" --steps 20000 "${metadrive[@]}"
      ;;
    1r)
      # Only the tasks whose entries still name that build: the others were reproduced already.
      mapfile -t todo < <(modified "${others[@]}")
      [ ${#todo[@]} -eq 0 ] || run --reproduce --methods "bc-all bc-safe" --steps 10000 "${todo[@]}"
      mapfile -t todo < <(modified "${metadrive[@]}")
      [ ${#todo[@]} -eq 0 ] || run --reproduce --methods "bc-all bc-safe" --steps 20000 "${todo[@]}"
      ;;
    2)
      # Longest models first, so the pool ends on short ones (data/reference_entries.sh trains all of a run's tasks
      # in one pool); BallRun's CAPS beside the rest rather than alone after them.
      run "${offline[@]}" --methods "bearl cdt cpq bcql coptidice caps" "${six[@]:1}"
      run "${offline[@]}" --methods "caps bearl cdt cpq bcql coptidice" --caps-steps 20000 OfflineBallRun-v0
      ;;
    3)
      bc=(--steps-for bc-all=10000 --steps-for bc-safe=10000)  # phase 1's budget
      run --seeds "1 2" "${offline[@]}" "${bc[@]}" --methods "bearl cdt cpq bcql coptidice bc-safe bc-all caps" \
        OfflineCarCircle-v0
      run --seeds "1 2" "${offline[@]}" "${bc[@]}" --methods "caps bearl cdt cpq bcql coptidice bc-safe bc-all" \
        --caps-steps 20000 OfflineBallRun-v0
      ;;
    4)
      run --methods "fisor lspc" --steps-for fisor=500 --steps-for lspc=2000 "${six[@]:0:4}"
      run --methods "fisor lspc" --steps-for fisor=500 --steps-for lspc=2000 "${six[@]:4}"
      ;;
    *) echo "no phase $phase" >&2; exit 2 ;;
  esac
done
