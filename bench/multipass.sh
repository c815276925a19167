#!/usr/bin/env bash
# Benchmark: the methods whose action takes several network passes (FISOR's diffusion sampler, LSPC's latent
# policy), side by side in one run, on the committed OfflineBallRun-v0 starter:
#   - training: one step of `dsrl-train fisor` (batch 2048: two actor halves of 1024, critics on 256; release, one
#     thread, its own timer over the steps after the first) and of `dsrl-train lspc` (batch 1024), beside one step
#     of LSPC's own PyTorch code (bench/multipass_step_torch.py, `lspc_iql.py` imported from the clone LSPC_REPO
#     names; without it that column is empty). FISOR's code is JAX, which this machine does not have: its column is
#     empty.
#   - scoring: `dsrl-admin evaluate` (one release worker, 10 episodes, one session of 10 environments) of FISOR's
#     checkpoint at its published settings (16 candidates × 5 denoising steps per action), of LSPC's and of BC-All's
#     (one MLP pass per action), each trained 2 steps: the wall time per environment step of the whole evaluation,
#     simulator included, so the difference to BC-All is what the extra passes cost.
# Prints a Markdown table (bench/out/multipass.md; into BENCHMARKS.md at the documented 20 steps) with the CPU and
# the load average at the start.
# Usage: bench/multipass.sh [STEPS=20]     LSPC_REPO=<clone of LSPC-Safe-Offline-RL> for LSPC's PyTorch column
set -euo pipefail
case ${1:-} in -h|--help) sed -n "2,15p" "$0"; exit 0 ;; esac
cd "$(dirname "$0")/.."
steps=${1:-20}
if [ -n "${LSPC_REPO:-}" ] && ! .venv-bench/bin/python -c "import torch, fsrl, tqdm" 2>/dev/null; then
  # bench/offline_step.sh's environment: PyTorch and fast-safe-rl (which lspc_iql.py imports for its logger).
  echo "making .venv-bench (bench/requirements-torch.txt) for LSPC's PyTorch column" >&2
  [ -x .venv-bench/bin/python ] || python3 -m venv .venv-bench
  .venv-bench/bin/pip install -q -r bench/requirements-torch.txt >&2
  .venv-bench/bin/pip install -q --no-deps osrl-lib==0.1.0 fast-safe-rl==0.1.0 >&2
fi
sim/setup.sh >&2
export PYO3_PYTHON="${PYO3_PYTHON:-$(command -v "${PYTHON:-python3}")}"
echo "building the release dsrl-train, dsrl-admin and dsrl-sim-worker" >&2
cargo build --release --locked -p dsrl-train -p dsrl-admin -p dsrl-sim --bins >&2
bin=${CARGO_TARGET_DIR:-target}/release
source bench/lib.sh  # the load is read after the build
task=OfflineBallRun-v0
data=$(ls data/starter/$task/*.parquet)
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-multipass-bench.XXXXXX")
trap 'rm -rf "$work"' EXIT
mkdir -p bench/out
# ms a step of `dsrl-train $1` from its own timer, its first step left out.
candle_step() {
  "$bin/dsrl-train" "$1" --task "$task" --dataset "$data" --steps $((steps + 1)) --out "$work/train" >&2
  python3 -c "import json; t=json.load(open('$work/train/$1/policy.json'))['training']; \
print('%.1f' % (1000*(t['seconds']-t['first_step_seconds'])/(t['steps']-1)))"
}
fisor=$(candle_step fisor)
lspc=$(candle_step lspc)
torch_lspc=–
torch_version=
if [ -n "${LSPC_REPO:-}" ]; then
  torch_version=$(.venv-bench/bin/python -c "import torch; print(torch.__version__)")
  torch_lspc=$(cd bench && LSPC_REPO=$LSPC_REPO ../.venv-bench/bin/python multipass_step_torch.py "../$data" \
    --steps "$steps" --threads 1 | python3 -c "import json,sys; print('%.1f' % json.load(sys.stdin)['ms_per_step'])")
fi
# ms per environment step of a whole evaluation of the checkpoint $1 (10 episodes, one session of 10 environments).
per_env_step() {
  "$bin/dsrl-admin" evaluate "$1" --workers 1 --episodes 10 --envs-per-session 10 --sessions 1 --json \
    > "$work/eval.json"
  python3 -c "import json; r=json.load(open('$work/eval.json')); eps=r.get('episodes') or r['thresholds'][0]['episodes']; \
print('%.2f' % (1000*r['wall_seconds']/sum(e['length'] for e in eps)))"
}
"$bin/dsrl-train" bc --mode all --task "$task" --dataset "$data" --steps 2 --out "$work/eval" >&2
"$bin/dsrl-train" fisor --task "$task" --dataset "$data" --steps 2 --out "$work/eval" >&2
"$bin/dsrl-train" lspc --task "$task" --dataset "$data" --steps 2 --out "$work/eval" >&2
bc_eval=$(per_env_step "$work/eval/bc-all")
fisor_eval=$(per_env_step "$work/eval/fisor")
lspc_eval=$(per_env_step "$work/eval/lspc")
ratio() { python3 -c "print('%.1f' % ($1 / $2))"; }
{
  echo "| method | training, candle 1 thread (ms/step) | training, its own code ${torch_version:+(PyTorch $torch_version) }1 thread (ms/step) | scoring (ms per environment step) | scoring / BC-All's |"
  echo "|---|---|---|---|---|"
  echo "| FISOR (batch 2048; 16 candidates × 5 steps) | $fisor | – (JAX) | $fisor_eval | $(ratio "$fisor_eval" "$bc_eval") |"
  echo "| LSPC (batch 1024) | $lspc | $torch_lspc | $lspc_eval | $(ratio "$lspc_eval" "$bc_eval") |"
  echo "| BC-All (one MLP pass) | – | – | $bc_eval | 1.0 |"
  echo
  echo "candle: the dsrl-train of \`$(python3 -c "import json; print(json.load(open('$work/train/fisor/policy.json'))['training']['code_commit'])")\`;"
  echo "$steps training steps after a first one, on the $task starter; scoring: 10 episodes on one release worker."
  echo "CPU: $(cpu_model) ($(nproc) cores), AVX-512: $(has_avx512). Load average at start: $bench_load. Measured $(date -u +%F)."
} > bench/out/multipass.md
cat bench/out/multipass.md
if [ "$steps" = 20 ]; then
  bench_section multipass.sh bench/out/multipass.md
fi
