#!/usr/bin/env bash
# The leaderboard's reference entries: the paper's seven baselines trained in candle by dsrl-train on each task's
# hosted dataset (fetched from the server, `latest`, into the dataset cache) and scored by that server's leaderboard
# with the paper's protocol (3 thresholds x 20 held episodes):
#   BC-All, BC-Safe (spec 5.5), CDT (5.4), BCQ-Lag (5.6), BEAR-Lag (5.7), CPQ and COptiDICE (5.8),
# with OSRL's networks and hyperparameters; per-threshold methods train one model per benchmark threshold, CDT one
# model conditioned on OSRL's return targets (data/cdt_targets.csv). Beyond the paper: CAPS (`caps`, AAAI 2025), one
# model given each threshold as its episode's cost budget; not in the default --methods.
# First every model is trained, --jobs at a time: one job per (task, seed, method, threshold) for the per-threshold
# methods (each model is seeded on its own, so the weights do not depend on --jobs), one per (task, seed) for BC-All,
# CDT and CAPS; each job is one single-threaded dsrl-train. Then the entries are submitted and waited for in turn, so
# one submission is in flight at a time; a server's daily quota (leaderboard.submissions_per_day, default 10) must
# allow 7 per task and seed (DSRL__LEADERBOARD__SUBMISSIONS_PER_DAY on a server you run).
# Needs DSRL_SERVER and a user token in DSRL_TOKEN (`dsrl-client admin create-user reference`).
#
# Usage: data/reference_entries.sh [--steps N] [--cdt-steps N] [--batch-size B] [--seeds "0 1 2"] [--jobs J]
#                                  [--methods "bc-all bc-safe cdt bcql bearl cpq coptidice caps"] TASK...
#   --steps N        gradient steps per model (default 100000, OSRL's; BEAR-Lag trains 3 N as OSRL's 300000)
#   --cdt-steps N    CDT's steps (default: --steps)
#   --caps-steps N   CAPS's steps (default: --steps)
#   --batch-size B   instead of OSRL's (512; CDT 2048), recorded with each model
#   --jobs J         models trained at once (default 1); one core each
#   e.g. data/reference_entries.sh --steps 2000 --cdt-steps 50 --jobs 16 OfflineBallRun-v0 OfflineCarRun-v0
# Every model records its budget, seed, dataset version and settings in policy.json; the leaderboard shows them.
set -euo pipefail
steps=100000 cdt_steps= caps_steps= batch_size= seeds="0" jobs=1 methods="bc-all bc-safe cdt bcql bearl cpq coptidice" tasks=()
while [ $# -gt 0 ]; do
  case $1 in
    --steps) steps=$2; shift 2 ;;
    --cdt-steps) cdt_steps=$2; shift 2 ;;
    --caps-steps) caps_steps=$2; shift 2 ;;
    --batch-size) batch_size=$2; shift 2 ;;
    --seeds) seeds=$2; shift 2 ;;
    --jobs) jobs=$2; shift 2 ;;
    --methods) methods=$2; shift 2 ;;
    -h|--help) sed -n '2,24p' "$0"; exit 0 ;;
    *) tasks+=("$1"); shift ;;
  esac
done
[ ${#tasks[@]} -gt 0 ] || { echo "name at least one task" >&2; exit 2; }
[[ $jobs =~ ^[1-9][0-9]*$ ]] || { echo "--jobs takes a positive count, not '$jobs'" >&2; exit 2; }
: "${DSRL_SERVER:?set DSRL_SERVER}" "${DSRL_TOKEN:?set DSRL_TOKEN to a user token}"
cdt_steps=${cdt_steps:-$steps}
caps_steps=${caps_steps:-$steps}
train=${DSRL_TRAIN:-dsrl-train}
client=${DSRL_CLIENT:-dsrl-client}
out=${OUT:-policies}
catalog=$(dirname "$0")/tasks.csv

# name and dsrl-train arguments of a method (after --task ...); whether it trains per threshold
method_name() {
  case $1 in
    bc-all) echo BC-All ;; bc-safe) echo BC-Safe ;; cdt) echo CDT ;; bcql) echo BCQ-Lag ;;
    bearl) echo BEAR-Lag ;; cpq) echo CPQ ;; coptidice) echo COptiDICE ;; caps) echo CAPS ;;
    *) echo "unknown method $1" >&2; exit 2 ;;
  esac
}
for method in $methods; do method_name "$method" >/dev/null; done
thresholds() {
  local t
  t=$(awk -F, -v task="$1" '$1 == task { print $12 }' "$catalog")
  [ -n "$t" ] || { echo "$1 is not in $catalog" >&2; exit 2; }
  echo "${t//;/ }"
}

# Every training job, one line each: task seed method threshold (- where the method is trained once).
units=()
for task in "${tasks[@]}"; do
  kappas=$(thresholds "$task")
  for seed in $seeds; do
    for method in $methods; do
      case $method in
        bc-all | cdt | caps) units+=("$task $seed $method -") ;;
        *) for kappa in $kappas; do units+=("$task $seed $method $kappa"); done ;;
      esac
    done
  done
done

train_unit() {
  local task=$1 seed=$2 method=$3 kappa=$4 args
  args=(--task "$task" --server "$DSRL_SERVER" --seed "$seed" --out "$out/$task/seed-$seed")
  [ -z "$batch_size" ] || args+=(--batch-size "$batch_size")
  [ "$kappa" = - ] || args+=(--cost-threshold "$kappa")
  case $method in
    bc-all) "$train" bc --mode all --steps "$steps" "${args[@]}" ;;
    bc-safe) "$train" bc --mode safe --steps "$steps" "${args[@]}" ;;
    cdt) "$train" cdt --steps "$cdt_steps" "${args[@]}" ;;
    caps) "$train" caps --steps "$caps_steps" "${args[@]}" ;;
    bearl) "$train" bearl --steps $((3 * steps)) "${args[@]}" ;;
    *) "$train" "$method" --steps "$steps" "${args[@]}" ;;
  esac
}

# Each task's dataset is fetched once before the jobs start, so parallel jobs read one verified cached file instead
# of racing to download it.
for task in "${tasks[@]}"; do "$client" fetch "$task" >&2; done
echo "training ${#units[@]} models, $jobs at a time" >&2
# A failed job stops new ones from starting (exit 255), and the script stops before submitting anything.
export -f train_unit
export steps cdt_steps caps_steps batch_size train out DSRL_SERVER
printf '%s\n' "${units[@]}" | xargs -P "$jobs" -L 1 bash -c 'train_unit "$@" || exit 255' train_unit

for task in "${tasks[@]}"; do
  for seed in $seeds; do
    for method in $methods; do
      name=$(method_name "$method") model=$out/$task/seed-$seed/$method
      echo "$task seed $seed: submitting $name ($model)" >&2
      "$client" submit "$model" --task "$task" --name "$name" --wait
    done
  done
done
