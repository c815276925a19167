#!/usr/bin/env bash
# OSRL's own examples/train/train_bc.py, run on this service's data with only its import lines changed
# (`import dsrl` -> `import dsrl_client as dsrl`, `from dsrl.X` -> `from dsrl_client.X`, and OSRL's own scoping bug
# below); the trained BC actor is
# then exported with dsrl_client.export_policy and scored by the leaderboard (tests/parity/osrl_train_bc_submit.py).
# Kept out of CI (scripts/test.sh): it needs PyTorch (~5 GB with the CUDA libraries PyPI's wheel brings) and an OSRL
# checkout. Its last recorded result is in README.md ("The Python package", checked with OSRL).
#
#   tests/parity/osrl_train_bc.sh [TASK [STEPS]]        default: OfflineCarCircle-v0, 200 update steps
#
# Environment:
#   DSRL_OSRL_CHECK_DIR  state (the venv, the OSRL clone, the run's logs); default ~/.dsrl/osrl-check
#   OSRL_GIT             where to clone OSRL from (default https://github.com/liuzuxin/OSRL), checked out at the
#                        commit pinned below
#   DSRL_SERVER          a running service to use, with DSRL_ADMIN_TOKEN (it creates a user). Default: a fresh
#                        dsrl-server on loopback (release build) serving the task's starter dataset, stopped at the end.
set -euo pipefail
cd "$(dirname "$0")/../.."
root=$PWD
task=${1:-OfflineCarCircle-v0}
steps=${2:-200}
state=${DSRL_OSRL_CHECK_DIR:-$HOME/.dsrl/osrl-check}
osrl_commit=03a4586463690566ec8d7830ca4027b46d4ad02f
mkdir -p "$state"
say() { echo "osrl-check: $*" >&2; }

# 1. The Python environment: the Bullet simulators at the workers' pins, PyTorch, OSRL and what its training script
#    imports (osrl-lib and fast-safe-rl with --no-deps: their own pins ask for torch 1.13 and more), and this package.
venv=$state/venv
if [ ! -x "$venv/bin/python" ]; then
  say "creating $venv"
  "${PYTHON:-python3}" -m venv "$venv"
fi
requirements=(-c sim/python/constraints.txt bullet-safety-gym==1.4.0 torch==2.15.0 safetensors==0.8.0
  pyrallis==0.3.1 scipy==1.11.4 tqdm==4.67.1 PyYAML==6.0.2 wandb==0.19.11 tensorboard==2.19.0)
want=$(printf '%s\n' "${requirements[@]}" | cat - sim/python/constraints.txt | sha256sum | cut -d' ' -f1)
pip=("$venv/bin/python" -m pip install --quiet --disable-pip-version-check)
if [ "$(cat "$venv/.requirements.sha256" 2>/dev/null)" != "$want" ]; then
  say "installing PyTorch, OSRL's training imports and Bullet-Safety-Gym into $venv (a few minutes the first time)"
  "${pip[@]}" "${requirements[@]}"
  "${pip[@]}" --no-deps osrl-lib==0.1.0 fast-safe-rl==0.1.0
  echo "$want" > "$venv/.requirements.sha256"
fi
say "building and installing the Python package and the simulator adapter (pip install ./client/python ./sim/python)"
PYO3_PYTHON=$venv/bin/python "${pip[@]}" -c sim/python/constraints.txt ./client/python ./sim/python

# 2. OSRL at the pinned commit, its example scripts copied and only their dsrl imports changed.
osrl=$state/OSRL
if [ ! -d "$osrl/.git" ]; then
  say "cloning OSRL into $osrl"
  git clone --quiet "${OSRL_GIT:-https://github.com/liuzuxin/OSRL}" "$osrl"
fi
git -C "$osrl" -c advice.detachedHead=false checkout --quiet "$osrl_commit"
run=$state/run
rm -rf "$run"
mkdir -p "$run"
cp -r "$osrl/examples" "$run/"
script=examples/train/train_bc.py
# One more import line goes: OSRL's `if "Metadrive" in args.task: import gym` inside train() makes `gym` a local
# name, so `gym.make` fails with UnboundLocalError for every other task, with DSRL too (OSRL's PR #18 fixed this in
# the eval scripts only). dsrl_client registers the MetaDrive ids with gymnasium like the others.
sed -i -e 's/^import dsrl$/import dsrl_client as dsrl/' -e 's/^from dsrl\.\([a-z_]*\) import/from dsrl_client.\1 import/' \
  -e 's/^\( *\)import gym$/\1pass  # was: import gym/' "$run/$script"
say "the change to OSRL's $script:"
diff -u "$osrl/$script" "$run/$script" >&2 || true
changed=$(diff "$osrl/$script" "$run/$script" | grep -c '^[<>]' || true)
imports=$(diff "$osrl/$script" "$run/$script" | grep -Ec '^[<>] (import dsrl|from dsrl| +import gym$| +pass  # was: import gym$)' || true)
if [ "$changed" -eq 0 ] || [ "$changed" -ne "$imports" ]; then
  say "expected only import lines to change ($changed changed lines, $imports of them imports)"
  exit 1
fi

# 3. The service: the one given, or a fresh server serving the task's starter dataset.
tmp=$(mktemp -d)
server_pid=
cleanup() {
  [ -n "$server_pid" ] && kill "$server_pid" 2>/dev/null && wait "$server_pid" 2>/dev/null
  rm -rf "$tmp"
}
trap cleanup EXIT
if [ -z "${DSRL_SERVER:-}" ]; then
  say "building the release server (cargo build --release -p dsrl-server -p dsrl-sim)"
  cargo build --release --locked -p dsrl-server -p dsrl-sim
  mkdir -p "$tmp/starter/$task"
  ln -s "$root/data/starter/$task"/* "$tmp/starter/$task/"
  "${CARGO_TARGET_DIR:-target}/release/dsrl-server" --listen 127.0.0.1:0 --data-dir "$tmp/server" \
    --starter-datasets "$tmp/starter" > "$tmp/server.out" 2> "$state/server.log" &
  server_pid=$!
  for _ in $(seq 600); do
    grep -q "listening on" "$tmp/server.out" 2>/dev/null && break
    kill -0 "$server_pid" 2>/dev/null || { say "dsrl-server exited; see $state/server.log"; exit 1; }
    sleep 0.5
  done
  DSRL_SERVER=$(sed -n 's/^dsrl-server listening on //p' "$tmp/server.out")
  [ -n "$DSRL_SERVER" ] || { say "dsrl-server did not start in 5 minutes; see $state/server.log"; exit 1; }
  DSRL_ADMIN_TOKEN=$(cat "$tmp/server/admin-token")
  say "dsrl-server at $DSRL_SERVER (log: $state/server.log)"
fi
export DSRL_SERVER DSRL_ADMIN_TOKEN
export DSRL_DATASET_DIR=$state/datasets

# 4. OSRL trains (its defaults for the task, but STEPS update steps; it evaluates once, at the last step, on the real
#    simulator through dsrl_client's env), logging offline.
say "OSRL train_bc: $task, $steps update steps"
(cd "$run" && WANDB_MODE=disabled WANDB_SILENT=true PYTHONPATH=. PYTHONWARNINGS=ignore "$venv/bin/python" "$script" \
  --task "$task" --update_steps "$steps" --num_workers 0 --device cpu --threads "$(nproc)" --logdir "$run/logs")

# 5. Its checkpoint exported and scored by the leaderboard.
say "exporting OSRL's checkpoint and submitting it"
OSRL_COMMIT=$osrl_commit PYTHONWARNINGS=ignore "$venv/bin/python" tests/parity/osrl_train_bc_submit.py "$run/logs" "$task" "$state/policy" \
  | tee "$state/result.json"
