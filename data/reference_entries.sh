#!/usr/bin/env bash
# The leaderboard's reference entries: the paper's seven baselines trained in candle by dsrl-train on each task's
# hosted dataset (fetched from the server, `latest`, into the dataset cache) and scored by that server's leaderboard
# with the paper's protocol (3 thresholds x 20 held episodes):
#   BC-All, BC-Safe (spec 5.5), CDT (5.4), BCQ-Lag (5.6), BEAR-Lag (5.7), CPQ and COptiDICE (5.8),
# with OSRL's networks and hyperparameters; per-threshold methods train one model per benchmark threshold, CDT one
# model conditioned on OSRL's return targets (data/cdt_targets.csv). Beyond the paper: CAPS (`caps`, AAAI 2025), one
# model given each threshold as its episode's cost budget; not in the default --methods. Each entry is submitted and waited for in turn,
# so one submission is in flight at a time; a server's daily quota (leaderboard.submissions_per_day, default 10)
# must allow 7 per task and seed (DSRL__LEADERBOARD__SUBMISSIONS_PER_DAY on a server you run).
# Needs DSRL_SERVER and a user token in DSRL_TOKEN (`dsrl-client admin create-user reference`).
#
# Usage: data/reference_entries.sh [--steps N] [--cdt-steps N] [--batch-size B] [--seeds "0 1 2"]
#                                  [--methods "bc-all bc-safe cdt bcql bearl cpq coptidice caps"] TASK...
#   --steps N        gradient steps per model (default 100000, OSRL's; BEAR-Lag trains 3 N as OSRL's 300000)
#   --cdt-steps N    CDT's steps (default: --steps)
#   --caps-steps N   CAPS's steps (default: --steps)
#   --batch-size B   instead of OSRL's (512; CDT 2048), recorded with each model
#   e.g. data/reference_entries.sh --steps 2000 --cdt-steps 50 OfflineBallRun-v0 OfflineCarRun-v0
# Every model records its budget, seed, dataset version and settings in policy.json; the leaderboard shows them.
set -euo pipefail
steps=100000 cdt_steps= caps_steps= batch=() seeds="0" methods="bc-all bc-safe cdt bcql bearl cpq coptidice" tasks=()
while [ $# -gt 0 ]; do
  case $1 in
    --steps) steps=$2; shift 2 ;;
    --cdt-steps) cdt_steps=$2; shift 2 ;;
    --caps-steps) caps_steps=$2; shift 2 ;;
    --batch-size) batch=(--batch-size "$2"); shift 2 ;;
    --seeds) seeds=$2; shift 2 ;;
    --methods) methods=$2; shift 2 ;;
    -h|--help) sed -n '2,20p' "$0"; exit 0 ;;
    *) tasks+=("$1"); shift ;;
  esac
done
[ ${#tasks[@]} -gt 0 ] || { echo "name at least one task" >&2; exit 2; }
: "${DSRL_SERVER:?set DSRL_SERVER}" "${DSRL_TOKEN:?set DSRL_TOKEN to a user token}"
cdt_steps=${cdt_steps:-$steps}
caps_steps=${caps_steps:-$steps}
train=${DSRL_TRAIN:-dsrl-train}
client=${DSRL_CLIENT:-dsrl-client}
out=${OUT:-policies}
for task in "${tasks[@]}"; do
  for seed in $seeds; do
    dir=$out/$task/seed-$seed
    for method in $methods; do
      common=(--task "$task" --server "$DSRL_SERVER" --seed "$seed" --out "$dir" "${batch[@]}")
      case $method in
        bc-all) name=BC-All; "$train" bc --mode all --steps "$steps" "${common[@]}"; model=$dir/bc-all ;;
        bc-safe) name=BC-Safe; "$train" bc --mode safe --steps "$steps" "${common[@]}"; model=$dir/bc-safe ;;
        cdt) name=CDT; "$train" cdt --steps "$cdt_steps" "${common[@]}"; model=$dir/cdt ;;
        bcql) name=BCQ-Lag; "$train" bcql --steps "$steps" "${common[@]}"; model=$dir/bcql ;;
        bearl) name=BEAR-Lag; "$train" bearl --steps $((3 * steps)) "${common[@]}"; model=$dir/bearl ;;
        cpq) name=CPQ; "$train" cpq --steps "$steps" "${common[@]}"; model=$dir/cpq ;;
        caps) name=CAPS; "$train" caps --steps "$caps_steps" "${common[@]}"; model=$dir/caps ;;
        coptidice) name=COptiDICE; "$train" coptidice --steps "$steps" "${common[@]}"; model=$dir/coptidice ;;
        *) echo "unknown method $method" >&2; exit 2 ;;
      esac
      echo "$task seed $seed: submitting $name ($model)" >&2
      "$client" submit "$model" --task "$task" --name "$name" --wait
    done
  done
done
