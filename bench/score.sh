#!/usr/bin/env bash
# Benchmark: wall time to score one leaderboard submission (the paper's protocol: 3 cost thresholds x 20 episodes)
# on OfflineBallCircle-v0 (SafetyBallCircle-v0, 200-step episodes), side by side in one run:
#   - dsrl: a release dsrl-server with two local simulator workers (one per core) scores a BC-All checkpoint
#     submitted with `dsrl-client submit --wait`; timed from the submit call until the submission reads `finished`
#     (the evaluator that ends it wakes the waiting request), so it includes the upload, the checks, the
#     queue and storing all 60 episodes;
#   - reference: a sequential in-process Python loop like OSRL's evaluation (tests/parity/evaluate_in_python.py
#     --one-env: one env, one episode after another, NumPy forward pass per step, one BLAS thread as the workers
#     use) playing the same checkpoint for 60 episodes, twice: on the simulators' own Python as published
#     (--library-code), which is the loop a researcher runs and the goal's reference, and with dsrl_sim's
#     speed-ups (sim/python/dsrl_sim/speedups.py), which the workers run, so the table shows what the service's
#     own layout gains apart from the faster simulator code.
#   - the same submission on a second server whose every step goes through the server and a policy process
#     (`leaderboard.act_in_workers_max_multiply_adds = 0`, the layout before the policy acted in the workers), with the same seed
#     secret: its episodes must equal the first server's, every one, or the script fails;
#   - the machine's ceiling for any two-process layout: two of the first loop at once, one per core (a host whose
#     cores slow each other, as hyperthreads or a busy host do, shows it below 2x).
# The checkpoint is BC-All trained by dsrl-train on the committed BallCircle starter (2000 steps; its quality does
# not matter here, only that both sides play the same network). Prints a Markdown table (bench/out/score.md, and into
# BENCHMARKS.md at 3 rounds with the default sessions) with the machine and whether the goal was met, and a second
# table of where the time goes: CPU seconds per simulator worker, of the server and of its policy processes, beside
# the loop's.
# Usage: bench/score.sh [ROUNDS=3]   (SKIP_BUILD=1: play the binaries already built)
set -euo pipefail
cd "$(dirname "$0")/.."
source bench/lib.sh
rounds=${1:-3}
sim/setup.sh >&2
export PYO3_PYTHON="${PYO3_PYTHON:-$(command -v "${PYTHON:-python3}")}"
# SKIP_BUILD=1 plays the binaries already in $CARGO_TARGET_DIR/release (another build's, for a before/after).
[ "${SKIP_BUILD:-0}" = 1 ] || cargo build --release --locked -p dsrl-server -p dsrl-client -p dsrl-train -p dsrl-sim --bins >&2
bin=$(realpath "${CARGO_TARGET_DIR:-target}/release")
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-score-bench.XXXXXX")
server_pid=
relay_pid=
cleanup() {
  [ -n "$server_pid" ] && kill "$server_pid" 2>/dev/null
  [ -n "$relay_pid" ] && kill "$relay_pid" 2>/dev/null
  rm -rf "$work"
}
trap cleanup EXIT
mkdir -p bench/out
task=OfflineBallCircle-v0
"$bin/dsrl-train" bc --task $task --mode all --dataset "$(ls data/starter/$task/*.parquet)" --steps 2000 \
  --out "$work/policy" >&2

# Two servers on free loopback ports, each with its own data folder and two workers, and one seed secret (the held
# seeds derive from it, so both play the same episodes): the relayed one (every step through the server) first.
export DSRL__LEADERBOARD__SEED_SECRET=bench-score-$(date +%s)
serve() {
  start_server "$work/$1" env DSRL__SIMULATORS__LOCAL_WORKERS=2 DSRL__LEADERBOARD__SUBMISSIONS_PER_DAY=1000 "${@:2}" \
    "$bin/dsrl-server" --listen 127.0.0.1:0 --data-dir "$work/$1/data" --starter-datasets "$work/none"
  for _ in $(seq 600); do
    [ "$(curl -s "$url/v1/simulators" | python3 -c 'import json,sys; print(json.load(sys.stdin)["healthy_workers"])')" = 2 ] && break
    sleep 0.2
  done
  # The checkpoint names the dataset version it was trained on, which the server must host: the committed starter.
  DSRL_ADMIN_TOKEN=$(cat "$work/$1/data/admin-token") "$bin/dsrl-client" --server "$url" admin ingest --task $task \
    "$(ls data/starter/$task/*.parquet)" >&2
  token=$(DSRL_ADMIN_TOKEN=$(cat "$work/$1/data/admin-token") "$bin/dsrl-client" --server "$url" admin create-user bench)
}
mkdir -p "$work/relayed" "$work/main"
serve relayed DSRL__LEADERBOARD__ACT_IN_WORKERS_MAX_MULTIPLY_ADDS=0
relay_pid=$server_pid relay_url=$url relay_token=$token
serve main
export DSRL_SERVER=$url DSRL_TOKEN=$token

# Where the time goes, per round: CPU seconds of each simulator worker, of the server itself and of the policy
# processes it ran and reaped (its children's time; the workers, also its children, live on and are not in it), the
# evaluator's own time from its log, and the Python loop's CPU seconds.
workers=$(pgrep -P "$server_pid" -f dsrl-sim-worker | sort -n | tr '\n' ' ')
[ "$(echo $workers | wc -w)" = 2 ] || { echo "expected the server's two simulator workers, found: $workers" >&2; exit 1; }
cpu_snapshot() {
  python3 -c '
import os, sys
hz = os.sysconf("SC_CLK_TCK")
for pid in sys.argv[1:]:
    f = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    print((int(f[11]) + int(f[12])) / hz, (int(f[13]) + int(f[14])) / hz, end=" ")
' "$server_pid" $workers
}
# The hypervisor's steal: CPU time this virtual machine was ready to run but not given (field 8 of /proc/stat's
# "cpu" line, in ticks summed over the cores), so a run on a host busy with other machines says so.
steal_ticks() { awk '/^cpu /{print $9; exit}' /proc/stat; }
steal_before=$(steal_ticks) rounds_started=$(date +%s.%N)
python_s=() fast_python_s=() dsrl_s=() relayed_s=() pair_s=() breakdown=()
for round in $(seq "$rounds"); do
  # A new network each round (max_action differs in the last digit), so the dedupe does not answer from the
  # first result; the play is the same.
  dir="$work/round-$round"; mkdir -p "$dir"
  cp "$work/policy/bc-all/policy.safetensors" "$dir/"
  python3 -c "import json,sys; c=json.load(open('$work/policy/bc-all/policy.json')); c['architecture']['max_action']=1.0-$round*1e-9; json.dump(c, open('$dir/policy.json','w'))"
  before=$(cpu_snapshot)
  log_lines=$(wc -l < "$work/main/server.log")
  start=$(date +%s.%N)
  # `--wait` holds one request open until the server sees the submission end (its evaluator wakes the request),
  # so timing takes next to no CPU from the two cores it measures; polling the full view did not: starting a curl
  # and a python3 per poll, or the server assembling the view each time, took a share of them.
  "$bin/dsrl-client" --json submit "$dir" --task $task --name "bench-$round" --wait > "$dir/submission.json"
  end=$(date +%s.%N)
  after=$(cpu_snapshot)
  id=$(python3 -c 'import json,sys; s=json.load(open(sys.argv[1])); print(s["id"]) if s["state"] == "finished" else sys.exit("submission %s %s" % (s["id"], s["state"]))' "$dir/submission.json")
  dsrl_s+=("$(python3 -c "print($end - $start)")")
  evaluated=$(sed -n "s/.*evaluation finished id=$id .*seconds=\([0-9.]*\).*/\1/p" "$work/main/server.log")
  # The workers' CPU seconds building this job's environments: each session's, from the workers' log lines (in
  # the server's log) written since the submission.
  built=$(tail -n +"$((log_lines + 1))" "$work/main/server.log" | python3 -c '
import re, sys
text = re.sub(r"\x1b\[[0-9;]*m", "", sys.stdin.read())
found = re.findall(r"session opened.*build_cpu_seconds=([0-9.e-]+)", text)
if not found:
    sys.exit("no session opened with build_cpu_seconds in the server log: a worker older than the script?")
print(sum(float(s) for s in found))')
  # The same checkpoint on the relayed server, which must play the same episodes.
  start=$(date +%s.%N)
  DSRL_SERVER=$relay_url DSRL_TOKEN=$relay_token "$bin/dsrl-client" --json submit "$dir" --task $task \
    --name "bench-$round" --wait > "$dir/relayed.json"
  end=$(date +%s.%N)
  relayed_s+=("$(python3 -c "print($end - $start)")")
  rid=$(python3 -c 'import json,sys; s=json.load(open(sys.argv[1])); print(s["id"]) if s["state"] == "finished" else sys.exit("relayed submission %s %s" % (s["id"], s["state"]))' "$dir/relayed.json")
  curl -s "$url/v1/submissions/$id" > "$dir/episodes.json"
  curl -s "$relay_url/v1/submissions/$rid" > "$dir/relayed-episodes.json"
  python3 - "$dir/episodes.json" "$dir/relayed-episodes.json" <<'PY'
import json, sys
keys = ("cost_threshold", "episode", "reward_return", "cost_return", "length")
a, b = (json.load(open(p)) for p in sys.argv[1:])
ea, eb = ([tuple(e[k] for k in keys) for e in s["episodes"]] for s in (a, b))
if ea != eb:
    diff = next(i for i, (x, y) in enumerate(zip(ea, eb)) if x != y) if len(ea) == len(eb) else "count"
    sys.exit("acting in the workers and through the server played different episodes (first difference: %s)" % diff)
PY
  # The loops' CPU seconds: each process's, as the parent sees them once it has exited.
  loop() {
    python3 -c '
import resource, subprocess, sys
with open(sys.argv[1], "w") as out:
    subprocess.run(sys.argv[2:], stdout=out, check=True)
r = resource.getrusage(resource.RUSAGE_CHILDREN)
print(r.ru_utime + r.ru_stime)
' "$1" env OPENBLAS_NUM_THREADS=1 .venv-sim/bin/python tests/parity/evaluate_in_python.py "$dir" \
      --sim-id SafetyBallCircle-v0 --episodes 60 --one-env "${@:2}"
  }
  start=$(date +%s.%N)
  loop_cpu=$(loop "$work/python.json" --library-code)
  end=$(date +%s.%N)
  python_s+=("$(python3 -c "print($end - $start)")")
  start=$(date +%s.%N)
  fast_loop_cpu=$(loop "$work/python-fast.json")
  end=$(date +%s.%N)
  fast_python_s+=("$(python3 -c "print($end - $start)")")
  # The machine's own ceiling for two processes: two of the first loop at once, one per core. Twice the loop's
  # episodes in this time is the most any two-process layout could gain here.
  start=$(date +%s.%N)
  loop "$work/pair-1.json" --library-code > /dev/null & first=$!
  loop "$work/pair-2.json" --library-code > /dev/null
  wait "$first"
  end=$(date +%s.%N)
  pair_s+=("$(python3 -c "print($end - $start)")")
  # Per round: the evaluator's own seconds, then CPU seconds of worker 1, worker 2, the server, its policy
  # processes, and the two loops.
  breakdown+=("$(python3 -c "
b, a = [float(x) for x in '$before'.split()], [float(x) for x in '$after'.split()]
print($evaluated, a[2] - b[2], a[4] - b[4], a[0] - b[0], a[1] - b[1], $loop_cpu, $fast_loop_cpu, $built)")")
done
steal_after=$(steal_ticks) rounds_ended=$(date +%s.%N)
steps=$(curl -s "$url/v1/submissions/$id" | python3 -c 'import json,sys; print(sum(e["length"] for e in json.load(sys.stdin)["episodes"]))')
steps_py=$(python3 -c "import json; print(sum(e['length'] for e in json.load(open('$work/python.json'))['episodes']))")
steps_py_fast=$(python3 -c "import json; print(sum(e['length'] for e in json.load(open('$work/python-fast.json'))['episodes']))")
median() { printf '%s\n' "$@" | sort -g | awk '{a[NR]=$1} END{printf "%.2f", a[int((NR+1)/2)]}'; }
rounded() { printf '%.2f ' "$@"; }
{
  machine_line
  echo
  echo "| scoring one submission on $task (3 thresholds x 20 episodes) | env-steps | median wall s ($rounds rounds) | each round, s |"
  echo "|---|---|---|---|"
  echo "| sequential in-process Python loop (OSRL-style, 1 env), the simulators' own code | $steps_py | $(median "${python_s[@]}") | $(rounded "${python_s[@]}")|"
  echo "| the same loop with dsrl_sim's speed-ups | $steps_py_fast | $(median "${fast_python_s[@]}") | $(rounded "${fast_python_s[@]}")|"
  echo "| dsrl-server: submit → finished (2 workers, ${DSRL__LEADERBOARD__ENVS_PER_SESSION:-5} envs per threshold) | $steps | $(median "${dsrl_s[@]}") | $(rounded "${dsrl_s[@]}")|"
  echo "| the same, every step through the server and a policy process (act_in_workers_max_multiply_adds 0; the same episodes) | $steps | $(median "${relayed_s[@]}") | $(rounded "${relayed_s[@]}")|"
  echo "| two of the first loop at once, one per core (each its own $steps_py env-steps) | $((2 * steps_py)) | $(median "${pair_s[@]}") | $(rounded "${pair_s[@]}")|"
  echo
  python3 -c "p, f, d = $(median "${python_s[@]}"), $(median "${fast_python_s[@]}"), $(median "${dsrl_s[@]}"); print('Goal (scoring at 1.8x the sequential loop or faster): %s, %.2fx the speed of the loop on the simulators\' own code; %.2fx the loop with the same speed-ups (medians).' % ('met' if p / d >= 1.8 else '**not met**', p / d, f / d))"
  python3 -c "p, r = $(median "${python_s[@]}"), $(median "${relayed_s[@]}"); print('Every step through the server instead: %.2fx the loop on the simulators\' own code (medians); its episodes equal the first server\'s in every round.' % (p / r))"
  python3 -c "
hz, cores = $(getconf CLK_TCK), $(nproc)
stolen = ($steal_after - $steal_before) / hz / (($rounds_ended - $rounds_started) * cores)
print('CPU time the hypervisor gave to other machines during the rounds (steal): %.0f%% of the %d cores.' % (100 * stolen, cores))"
  python3 -c "p, two = $(median "${python_s[@]}"), $(median "${pair_s[@]}"); print('The machine\'s ceiling for two processes: two loops at once play the episodes of one loop at %.2fx its speed (2.00x: the cores do not slow each other).' % (2 * p / two))"
  echo
  echo "Where the time goes, median over the rounds (CPU seconds from /proc, the loops' with their start and imports;"
  echo "the evaluator's seconds from its log, from claiming the job to storing its episodes; building envs: the"
  echo "Python thread's CPU seconds in building the job's environments, from the workers' log, part of their columns):"
  echo
  printf '%s\n' "${breakdown[@]}" | python3 -c '
import statistics, sys
rows = [[float(x) for x in line.split()] for line in sys.stdin if line.strip()]
m = [statistics.median(c) for c in zip(*rows)]
evaluated, w1, w2, server, policy, loop, fast_loop, built = m
print("| dsrl-server: evaluator s | CPU s: worker 1 | CPU s: worker 2 | of the workers\x27: building envs | CPU s: server | CPU s: policy processes | CPU s: all of dsrl | CPU s: the loop, own code | CPU s: the loop, speed-ups |")
print("|---|---|---|---|---|---|---|---|---|")
print("| %.2f | %.2f | %.2f | %.2f | %.2f | %.2f | %.2f | %.2f | %.2f |" % (evaluated, w1, w2, built, server, policy, w1 + w2 + server + policy, loop, fast_loop))
'
} > bench/out/score.md
cat bench/out/score.md
if [ "$rounds" = 3 ] && [ -z "${DSRL__LEADERBOARD__ENVS_PER_SESSION:-}" ]; then bench_section score.sh bench/out/score.md; fi
