#!/usr/bin/env bash
# The leaderboard's reference entries, as data: trains the paper's baselines with dsrl-train on each task's hosted
# dataset, has a dsrl leaderboard score them (held seeds; the task's 3 thresholds x 20 episodes), and writes each
# scored entry into the results file (data/reference/results.jsonl) with `dsrl-train reference-entry`: task, method,
# seed, budget, dataset version, code commit, checkpoint digest, protocol version and every episode. Every reference
# table in the documents is generated from that file (scripts/reference_tables.py), and every server imports it.
#   Methods: BC-All, BC-Safe (spec 5.5), CDT (5.4), BCQ-Lag (5.6), BEAR-Lag (5.7), CPQ and COptiDICE (5.8) with OSRL's
#   networks and hyperparameters, and beyond the paper (not in the default --methods) CAPS (AAAI 2025), FISOR
#   (ICLR 2024) and LSPC (ICLR 2025) with their own code's.
#   Per-threshold methods train one model per benchmark threshold, CDT one model conditioned on OSRL's return
#   targets (data/cdt_targets.csv), CAPS one model given each threshold as its episode's cost budget, FISOR and LSPC
#   one model for every threshold (neither reads it).
#
# Resumable: all state lives in --state (default ~/.dsrl/reference), outside the clone. A model whose training
# finished is not trained again (a marker names its budget); a submission already made is waited for, not made
# again; an entry the results file already holds, trained to the same budget on the dataset version hosted now, is
# neither trained nor submitted again, so a fresh machine resumes from the committed results. Kill it and run the
# same command again.
#
# Scoring server: $DSRL_SERVER with a user token in $DSRL_TOKEN (its daily quota must allow the entries), or, when
# DSRL_SERVER is unset, a private dsrl-server this script starts on the embedded defaults and the committed
# starters, with its state under <state>/server (its own held-seed secret, kept between runs), reference import
# off, quotas and the evaluation deadline lifted, --evaluators evaluators, simulator requests allowed
# $DSRL_REFERENCE_REQUEST_TIMEOUT_S seconds (900) and a job claimed up to 10 times; it is stopped at the end.
#
# Usage: data/reference_entries.sh [--steps N] [--cdt-steps N] [--caps-steps N] [--bearl-steps N] [--steps-for M=N]...
#                                  [--batch-size B] [--seeds "0 1 2"] [--jobs J] [--evaluators E] [--methods "..."]
#                                  [--state DIR] [--results FILE] [--train-only] [--reproduce] [--gpus G] TASK...
#   --steps N        gradient steps per model (default 100000, OSRL's); BEAR-Lag trains 3 N (OSRL's 300000)
#   --cdt-steps N    CDT's steps (default: --steps); --caps-steps N likewise; --bearl-steps N instead of 3 N
#   --steps-for M=N  steps of method M (e.g. cpq=5000), over the options above
#   --batch-size B   instead of OSRL's (512; CDT 2048), recorded with each model
#   --seeds "S..."   training seeds (default 0)
#   --jobs J         models trained at once (default 1); one core each
#   --methods "..."  of bc-all bc-safe cdt bcql bearl cpq coptidice caps fisor lspc (default: the first seven)
#   --train-only     train, submit nothing
#   --reproduce      train the entries already in the results file again from scratch (into <state>/reproduced) and
#                    submit nothing: an entry whose checkpoints come out with the digest it was scored with takes the
#                    new training record (the commit of this dsrl-train, its seconds), keeping its scoring; one that
#                    does not is left as it is and reported, and the script fails at the end. Give the budgets the
#                    entries were trained with.
#   --full-builds D  train on each task's full build instead of its starter: the private server hosts the finished
#                    build of every named task from D (dsrl-admin build's --root, e.g. ~/.dsrl/full) as the task's
#                    `latest`, uploaded and checked against its committed identity by `dsrl-admin build --server`
#                    (a task without a finished build stops the script before anything trains); use it with
#                    --results data/reference/full_builds.jsonl so starter-trained entries stay apart; its state
#                    defaults to ~/.dsrl/reference-full (a model's marker names its budget, not its dataset)
#   --gpus G         train on G GPUs (cuda:0 .. cuda:G-1, models dealt in turn; --jobs at a time in all) with a
#                    dsrl-train built by scripts/build-cuda.sh; every method
#   e.g. data/reference_entries.sh --steps 10000 --methods "bc-all bc-safe" OfflineBallRun-v0 OfflineCarRun-v0
# Binaries: dsrl-train, dsrl-client, dsrl-server (and dsrl-admin for --full-builds) from PATH (scripts/serve.sh links
# them), or $DSRL_TRAIN, $DSRL_CLIENT, $DSRL_SERVER_BIN, $DSRL_ADMIN.
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
steps=100000 cdt_steps= caps_steps= bearl_steps= batch_size= seeds="0" jobs=1 evaluators=1 train_only=no reproduce=no gpus=0
methods="bc-all bc-safe cdt bcql bearl cpq coptidice" tasks=() overrides=() full_builds=
state=
results=$repo/data/reference/results.jsonl
while [ $# -gt 0 ]; do
  case $1 in
    --steps) steps=$2; shift 2 ;;
    --cdt-steps) cdt_steps=$2; shift 2 ;;
    --caps-steps) caps_steps=$2; shift 2 ;;
    --bearl-steps) bearl_steps=$2; shift 2 ;;
    --steps-for) overrides+=("$2"); shift 2 ;;
    --batch-size) batch_size=$2; shift 2 ;;
    --seeds) seeds=$2; shift 2 ;;
    --jobs) jobs=$2; shift 2 ;;
    --evaluators) evaluators=$2; shift 2 ;;
    --methods) methods=$2; shift 2 ;;
    --state) state=$2; shift 2 ;;
    --results) results=$2; shift 2 ;;
    --train-only) train_only=yes; shift ;;
    --reproduce) reproduce=yes; shift ;;
    --gpus) gpus=$2; shift 2 ;;
    --full-builds) full_builds=$2; shift 2 ;;
    -h|--help) sed -n '2,48p' "$0"; exit 0 ;;
    *) tasks+=("$1"); shift ;;
  esac
done
[ ${#tasks[@]} -gt 0 ] || { echo "name at least one task" >&2; exit 2; }
if [ -z "$state" ]; then
  if [ -n "$full_builds" ]; then state=$HOME/.dsrl/reference-full; else state=${DSRL_REFERENCE_STATE:-$HOME/.dsrl/reference}; fi
fi
[[ $jobs =~ ^[1-9][0-9]*$ ]] || { echo "--jobs takes a positive count, not '$jobs'" >&2; exit 2; }
[[ $gpus =~ ^[0-9]+$ ]] || { echo "--gpus takes a count, not '$gpus'" >&2; exit 2; }
train=${DSRL_TRAIN:-dsrl-train}
client=${DSRL_CLIENT:-dsrl-client}
server_bin=${DSRL_SERVER_BIN:-dsrl-server}
admin=${DSRL_ADMIN:-dsrl-admin}
catalog=$repo/data/tasks.csv
if [ -n "$full_builds" ]; then
  [ -z "${DSRL_SERVER:-}" ] || { echo "--full-builds uploads to the private server: unset DSRL_SERVER" >&2; exit 2; }
  for task in "${tasks[@]}"; do
    compgen -G "$full_builds/$task/*.parquet" > /dev/null \
      || { echo "$task has no finished full build under $full_builds (dsrl-admin build $task)" >&2; exit 2; }
  done
fi
out=$state/policies
[ "$reproduce" = no ] || out=$state/reproduced/policies
mkdir -p "$state" "$out" "$state/submissions"

# name and dsrl-train arguments of a method (after --task ...); whether it trains per threshold
method_name() {
  case $1 in
    bc-all) echo BC-All ;; bc-safe) echo BC-Safe ;; cdt) echo CDT ;; bcql) echo BCQ-Lag ;;
    bearl) echo BEAR-Lag ;; cpq) echo CPQ ;; coptidice) echo COptiDICE ;; caps) echo CAPS ;;
    fisor) echo FISOR ;; lspc) echo LSPC ;;
    *) echo "unknown method $1" >&2; exit 2 ;;
  esac
}
for method in $methods; do
  method_name "$method" >/dev/null
done
method_steps() {
  local o
  for o in "${overrides[@]+"${overrides[@]}"}"; do
    [ "${o%%=*}" = "$1" ] && { echo "${o#*=}"; return; }
  done
  case $1 in
    cdt) echo "${cdt_steps:-$steps}" ;;
    caps) echo "${caps_steps:-$steps}" ;;
    bearl) echo "${bearl_steps:-$((3 * steps))}" ;;
    *) echo "$steps" ;;
  esac
}
thresholds() {
  local t
  t=$(awk -F, -v task="$1" '$1 == task { print $12 }' "$catalog")
  [ -n "$t" ] || { echo "$1 is not in $catalog" >&2; exit 2; }
  echo "${t//;/ }"
}

# The scoring server: the given one, or a private one. Its simulator requests may take up to $request_timeout
# seconds instead of a public server's 120: a sweep is a batch job, often at low priority beside other work, where
# building MetaDrive's scenes for a session has taken past 120 s; a slow scoring is fine, a failed one costs a rerun.
request_timeout=${DSRL_REFERENCE_REQUEST_TIMEOUT_S:-900}
# Every start of the private server re-claims the jobs it left running, and a public server fails a job on its third
# claim: here a stopped and resumed sweep is the usual cause, not a job that kills its evaluator.
max_attempts=10
server_pid= training=
# However the script ends (a failed model or scoring, a signal), nothing it started outlives it: models left training
# would go on against a server that is gone, beside the copies a rerun starts of them. The training job (xargs, its
# shells, their dsrl-train processes) is a process group of its own.
on_exit() {
  [ -z "$training" ] || kill -- "-$training" 2> /dev/null || true
  [ -z "$server_pid" ] || kill "$server_pid" 2>/dev/null || true
}
trap on_exit EXIT
if [ -z "${DSRL_SERVER:-}" ]; then
  port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
  mkdir -p "$state/server"
  echo "starting a private scoring server on 127.0.0.1:$port (state in $state/server, log $state/server.log)" >&2
  # No evaluation deadline to speak of (a day): the private server scores our own checkpoints at the lowest
  # priority, beside other work that can starve it for minutes, and a slow machine is not the checkpoint's fault.
  DSRL__SERVER__DATA_DIR=$state/server DSRL__SERVER__LISTEN=127.0.0.1:$port \
    DSRL__LEADERBOARD__DEADLINE_FACTOR=1000 DSRL__LEADERBOARD__MAX_EVALUATION_SECONDS=86400 \
    DSRL__LEADERBOARD__IMPORT_REFERENCE_RESULTS=false DSRL__LEADERBOARD__EVALUATORS=$evaluators \
    DSRL__LEADERBOARD__SUBMISSIONS_PER_DAY=1000000 DSRL__LEADERBOARD__CONCURRENT_SUBMISSIONS=1000000 \
    DSRL__LEADERBOARD__MAX_ATTEMPTS=$max_attempts DSRL__SIMULATORS__REQUEST_TIMEOUT_S=$request_timeout \
    "$server_bin" --starter-datasets "$repo/data/starter" >> "$state/server.log" 2>&1 &
  server_pid=$!
  export DSRL_SERVER=http://127.0.0.1:$port
  for _ in $(seq 1 600); do
    "$client" --server "$DSRL_SERVER" list >/dev/null 2>&1 && break
    kill -0 "$server_pid" 2>/dev/null || { echo "the scoring server exited; see $state/server.log" >&2; exit 1; }
    sleep 1
  done
  if [ ! -s "$state/user-token" ]; then
    DSRL_ADMIN_TOKEN=$(cat "$state/server/admin-token") "$client" admin create-user reference-trainer \
      > "$state/user-token.tmp"
    mv "$state/user-token.tmp" "$state/user-token"
  fi
  export DSRL_TOKEN=$(cat "$state/user-token")
  if [ -n "$full_builds" ]; then
    echo "hosting the full builds of ${tasks[*]} from $full_builds as their latest versions" >&2
    DSRL_ADMIN_TOKEN=$(cat "$state/server/admin-token") "$admin" build --root "$full_builds" --server "$DSRL_SERVER" \
      "${tasks[@]}" >&2
  fi
fi
: "${DSRL_TOKEN:?set DSRL_TOKEN to a user token of $DSRL_SERVER}"

# Train every task's models (--jobs at a time, one pool), submit each entry as soon as its models have trained (the
# server scores it while the rest train), and record every entry whose scoring has finished (checked every minute),
# so the results file grows as entries are scored.
# A model whose training finished leaves a marker naming its budget; a model trained to another budget is trained
# again.
marker_of() { echo "$out/$1/seed-$2/.trained-$3-$4-steps-$5-batch-${batch_size:-osrl}"; }
train_unit() {
  local task=$1 seed=$2 method=$3 kappa=$4 n=$5 device=$6 args marker
  marker=$(marker_of "$task" "$seed" "$method" "$kappa" "$n")
  [ -e "$marker" ] && return 0
  args=(--task "$task" --server "$DSRL_SERVER" --seed "$seed" --out "$out/$task/seed-$seed" --steps "$n")
  [ -z "$batch_size" ] || args+=(--batch-size "$batch_size")
  [ "$kappa" = - ] || args+=(--cost-threshold "$kappa")
  [ "$device" = cpu ] || args+=(--device "$device")
  # Run by xargs in a shell of its own, without errexit: a failed training must return here, before its marker.
  case $method in
    bc-all) "$train" bc --mode all "${args[@]}" ;;
    bc-safe) "$train" bc --mode safe "${args[@]}" ;;
    *) "$train" "$method" "${args[@]}" ;;
  esac || return 1
  rm -f "$out/$task/seed-$seed/.trained-$method-$kappa-"*
  touch "$marker"
}
export -f marker_of train_unit
export batch_size train out DSRL_SERVER

sub_of() { echo "$state/submissions/$1/seed-$2/$3"; }
# Keeps the final JSON of the submission whose state files start with $1: waiting for it (wait), or only when it
# has already ended (poll; returns 1 while it is queued or running).
finish() {
  [ -s "$1.json" ] && return 0
  if [ "${2:-wait}" = wait ]; then
    "$client" --json status "$(cat "$1.id")" --wait > "$1.json.tmp"
  else
    "$client" --json status "$(cat "$1.id")" > "$1.json.tmp"
    if python3 -c 'import json, sys; sys.exit(json.load(sys.stdin)["state"] in ("queued", "running"))' \
        < "$1.json.tmp"; then :; else rm -f "$1.json.tmp"; return 1; fi
  fi
  mv "$1.json.tmp" "$1.json"
}
# Writes a scored entry into the results file (once per scoring; dsrl-train replaces the same task, method, seed).
record() {
  local task=$1 seed=$2 method=$3 sub
  sub=$(sub_of "$task" "$seed" "$method")
  [ "$sub.recorded" -nt "$sub.json" ] && return 0
  "$train" reference-entry --model "$out/$task/seed-$seed/$method" --submission "$sub.json" \
    --method "$(method_name "$method")" --results "$results"
  touch "$sub.recorded"
}
# A scoring that failed for the service's sake (a simulator worker that stopped answering on an overloaded machine
# fails a job after its attempts) is submitted again, twice at most; a third failure, or one the leaderboard puts down
# to the checkpoint, stops the script with its reason.
failed_scoring() {
  local sub tries
  sub=$(sub_of "$1" "$2" "$3")
  python3 -c 'import json, sys; sys.exit(json.load(sys.stdin)["state"] != "failed")' < "$sub.json" || return 1
  tries=$(( $(cat "$sub.retries" 2> /dev/null || echo 0) + 1 ))
  echo "$1 seed $2: $(method_name "$3") submission $(cat "$sub.id") failed: $(python3 -c \
    'import json, sys; print(json.load(sys.stdin).get("reason") or "no reason given")' < "$sub.json")" >&2
  # The checkpoint's own failure would come again, and the server refuses the same checkpoint while that
  # submission stands.
  if python3 -c 'import json, sys; sys.exit(json.load(sys.stdin).get("failure") != "checkpoint")' < "$sub.json"; then
    echo "the leaderboard failed it as the checkpoint's fault: not submitted again" >&2; exit 1
  fi
  if [ "$tries" -gt 2 ]; then echo "giving up after $tries failed scorings" >&2; exit 1; fi
  echo "$tries" > "$sub.retries"
  rm -f "$sub.id" "$sub.json" "$sub.recorded"
}
in_flight=()   # "task seed method" of submissions not yet recorded, oldest first
unreproduced=()  # with --reproduce: "task seed S method" of entries whose retraining gave other checkpoints
record_finished() {
  local mode=$1 e task seed method left=()
  for e in "${in_flight[@]+"${in_flight[@]}"}"; do
    read -r task seed method <<< "$e"
    if finish "$(sub_of "$task" "$seed" "$method")" "$mode"; then
      if failed_scoring "$task" "$seed" "$method"; then
        submit "$task" "$seed" "$method"  # appends to in_flight, which this loop has already copied
        left+=("$e")
      else
        record "$task" "$seed" "$method"
      fi
    else
      left+=("$e")
    fi
  done
  in_flight=("${left[@]+"${left[@]}"}")
}
submit() {
  local task=$1 seed=$2 method=$3 name model sub answer id
  name=$(method_name "$method") model=$out/$task/seed-$seed/$method
  sub=$(sub_of "$task" "$seed" "$method")
  mkdir -p "$(dirname "$sub")"
  # A submission made for another training of this model is stale.
  if [ -e "$sub.id" ] && [ "$sub.id" -ot "$model" ]; then rm -f "$sub.id" "$sub.json" "$sub.recorded"; fi
  # So is an id kept from a scoring server whose state was reset since: it names someone else's submission.
  if [ -e "$sub.id" ] && ! "$client" --json status "$(cat "$sub.id")" 2> /dev/null | python3 -c \
      'import json, sys; d = json.load(sys.stdin); sys.exit(d["task"] != sys.argv[1] or d["name"] != sys.argv[2])' \
      "$task" "$name-seed$seed"; then
    rm -f "$sub.id" "$sub.json" "$sub.recorded"
  fi
  if [ ! -e "$sub.id" ]; then
    while true; do
      if answer=$("$client" --json submit "$model" --task "$task" --name "$name-seed$seed" 2> "$sub.err"); then
        python3 -c 'import json, sys; print(json.load(sys.stdin)["id"])' <<< "$answer" > "$sub.id"
        break
      elif id=$(grep -o 'as submission [0-9]*' "$sub.err" | grep -o '[0-9]*$'); then
        echo "$id" > "$sub.id"  # submitted before the script was stopped
        break
      elif grep -q 'queued or running' "$sub.err" && [ ${#in_flight[@]} -gt 0 ]; then
        record_finished wait  # the server's quota of submissions in flight: wait for those made
      else
        cat "$sub.err" >&2; exit 1
      fi
    done
    echo "$task seed $seed: $name submitted as $(cat "$sub.id")" >&2
  fi
  in_flight+=("$task $seed $method")
}

# Whether the results file holds the entry of task $1, seed $2, method $3 already (a fresh machine, whose --state is
# empty, resumes from the committed results), trained to $4 steps at this batch size on dataset version $5: then it
# is neither trained nor submitted again (with --reproduce, trained again all the same). Says why in $why.
recorded() {
  why=$(python3 - "$results" "$@" "$batch_size" <<'EOF'
import json, sys
path, task, seed, method, steps, version, batch = sys.argv[1:]
try:
    lines = open(path).read().splitlines()
except FileNotFoundError:
    sys.exit(1)
for line in lines:
    e = json.loads(line)
    if (e["task"], e["method"], str(e["seed"])) != (task, method, seed):
        continue
    t = e["training"]
    if t["steps"] != int(steps) or t["batch_size"] != (int(batch) if batch else t["osrl_batch_size"]):
        sys.exit(1)
    if e["dataset_version"] != version:
        sys.exit(1)
    print(f"{steps} steps, batch {t['batch_size']}, dataset {version[:12]}")
    sys.exit(0)
sys.exit(1)
EOF
  )
}

# The models of method $2 on task $1: "-" for the methods trained once, else the task's thresholds.
models_of() { case $2 in bc-all | cdt | caps | fisor | lspc) echo - ;; *) thresholds "$1" ;; esac; }
# Whether every model of task $1, seed $2, method $3 has finished training.
trained() {
  local kappa
  for kappa in $(models_of "$1" "$3"); do
    [ -e "$(marker_of "$1" "$2" "$3" "$kappa" "$(method_steps "$3")")" ] || return 1
  done
}
# Hands in each pending method whose models have all trained: submits it or, with --reproduce, checks it. A run
# stopped while models train then loses only those still training, not the finished methods'.
hand_in_trained() {
  local e task seed method left=()
  [ "$train_only" = no ] || return 0
  for e in "${pending[@]+"${pending[@]}"}"; do
    read -r task seed method <<< "$e"
    if ! trained "$task" "$seed" "$method"; then
      left+=("$e")
    elif [ "$reproduce" = yes ]; then
      "$train" reference-entry --reproduce --model "$out/$task/seed-$seed/$method" \
        --method "$(method_name "$method")" --results "$results" || unreproduced+=("$task seed $seed $method")
    else
      submit "$task" "$seed" "$method"
    fi
  done
  pending=("${left[@]+"${left[@]}"}")
}

# The device of the next model (in $device): the CPU, or the GPUs in turn.
dealt=0 device=cpu
next_device() {
  if [ "$gpus" -gt 0 ]; then device=cuda:$((dealt % gpus)) dealt=$((dealt + 1)); fi
}
# Every task's models train in one pool, --jobs at a time, task after task: a task's last models train beside the
# next task's first, so no core waits for a task (say, its third BEAR-Lag threshold) to finish.
units=() pending=() pooled=()
for task in "${tasks[@]}"; do
  "$client" fetch "$task" >&2  # fetched once, so parallel jobs read one verified cached file
  version=$("$client" --json show "$task" | python3 -c 'import json, sys; print(json.load(sys.stdin)["version"])')
  before=${#units[@]}
  for seed in $seeds; do
    for method in $methods; do
      n=$(method_steps "$method")
      if [ "$reproduce" = no ] && recorded "$task" "$seed" "$(method_name "$method")" "$n" "$version"; then
        echo "$task seed $seed: $(method_name "$method") is in $results already ($why); not trained again" >&2
        continue
      fi
      pending+=("$task $seed $method")
      for kappa in $(models_of "$task" "$method"); do
        next_device
        units+=("$task $seed $method $kappa $n $device")
      done
    done
  done
  [ ${#units[@]} -eq "$before" ] || pooled+=("$task")
done
if [ ${#units[@]} -gt 0 ]; then
  echo "$(date -u +%FT%TZ) training ${#units[@]} models ($jobs at a time) of ${pooled[*]} into $out" >&2
  # Every minute while they train: the methods whose models have all trained are handed in, and the entries scored
  # meanwhile are recorded. A failed job stops new ones from starting (exit 255), and the script stops with it.
  # The job runs in a process group of its own (job control on for its start), so that on exit the whole of it can
  # be stopped, even models a failed xargs left running.
  set -m
  xargs -P "$jobs" -L 1 bash -c 'train_unit "$@" || exit 255' train_unit < <(printf '%s\n' "${units[@]}") &
  training=$! polled=0
  set +m
  while kill -0 "$training" 2> /dev/null; do
    if [ "$SECONDS" -ge "$polled" ]; then hand_in_trained; record_finished poll; polled=$((SECONDS + 60)); fi
    sleep 1
  done
  wait "$training"
  training=
  hand_in_trained
  [ "$reproduce" = yes ] || record_finished poll
fi
[ "$train_only" = no ] || exit 0
if [ "$reproduce" = yes ]; then
  [ ${#unreproduced[@]} -eq 0 ] || { printf 'not reproduced: %s\n' "${unreproduced[@]}" >&2; exit 1; }
  echo "$(date -u +%FT%TZ) every entry reproduced; $results names the commit of $train" >&2
  exit 0
fi
record_finished wait
echo "$(date -u +%FT%TZ) every entry scored and recorded in $results" >&2
