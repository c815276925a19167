#!/usr/bin/env bash
# Benchmark: one training step of the five offline safe-RL baselines (BCQ-L, BEAR-L, CPQ, COptiDICE, CDT) side by side in
# one run, on the same data (the committed OfflineCarRun-v0 starter) with OSRL's CarRun settings (batch 512, hidden
# [256, 256], VAE hidden 400, cost threshold 10, each algorithm's own learning rates):
#   - candle: `dsrl-train <algo> --cost-threshold 10` (release build, one thread; the learner's own timer, which
#     includes drawing each batch, over all steps after the first: the first is the warm-up, as PyTorch's are);
#   - PyTorch on CPU (bench/offline_step_torch.py: OSRL's own model classes and Trainers, imported from the installed
#     osrl-lib package), one thread and all cores; batches built before the clock starts, a few untimed warm-up
#     steps first.
# PyTorch and OSRL live in their own environment, .venv-bench (bench/requirements-torch.txt, plus osrl-lib and
# fast-safe-rl installed with --no-deps: their own pins ask for torch 1.13, wandb, simulators), made on first use.
# Prints a Markdown table (also bench/out/offline_step.md) with the CPU, whether it has AVX-512 and the load average
# when the run started (other work on the machine slows every column). Usage: bench/offline_step.sh [STEPS=50]
# SKIP_BUILD=1 uses the dsrl-train already built instead of running cargo.
set -euo pipefail
cd "$(dirname "$0")/.."
steps=${1:-50}
warmup=${WARMUP:-5}
osrl_pins=(osrl-lib==0.1.0 fast-safe-rl==0.1.0)
if [ ! -x .venv-bench/bin/python ]; then
  python3 -m venv .venv-bench
  .venv-bench/bin/pip install -q -r bench/requirements-torch.txt >&2
fi
if ! .venv-bench/bin/python -c "import osrl, fsrl, gymnasium, scipy, tqdm, yaml" 2>/dev/null; then
  .venv-bench/bin/pip install -q -r bench/requirements-torch.txt >&2
  .venv-bench/bin/pip install -q --no-deps "${osrl_pins[@]}" >&2
fi
if [ "${SKIP_BUILD:-0}" != 1 ]; then
  export PYO3_PYTHON="${PYO3_PYTHON:-$(command -v "${PYTHON:-python3}")}"
  cargo build --release --locked -p dsrl-train --bins >&2
fi
bin=${CARGO_TARGET_DIR:-target}/release
data=$(ls data/starter/OfflineCarRun-v0/*.parquet)
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-offline-bench.XXXXXX")
trap 'rm -rf "$work"' EXIT
mkdir -p bench/out
threads=$(nproc)
load=$(cut -d' ' -f1-3 /proc/loadavg)
cpu=$(lscpu | sed -n 's/^Model name: *//p' | head -1)
if grep -q -m1 avx512 /proc/cpuinfo; then avx512=yes; else avx512=no; fi
torch_version=$(.venv-bench/bin/python -c "import torch; print(torch.__version__)")
ms() { python3 -c "import json,sys; print(json.loads(sys.stdin.read().strip().splitlines()[-1])['ms_per_step'])"; }
torch_step() { .venv-bench/bin/python bench/offline_step_torch.py "$data" --algo "$1" --steps "$steps" \
  --warmup "$warmup" --threads "$2" | ms; }
rows=()
cdt_steps=${CDT_STEPS:-3}
for algo in bcql bearl cpq coptidice cdt; do
  echo "== $algo" >&2
  if [ "$algo" = cdt ]; then
    # CDT is trained once (no threshold) at batch 2048 and takes seconds a step: fewer steps, one warm-up.
    "$bin/dsrl-train" cdt --task OfflineCarRun-v0 --dataset "$data" --steps $((cdt_steps + 1)) --out "$work" >&2
    policy=$work/cdt/policy.json
    torch1=$(.venv-bench/bin/python bench/offline_step_torch.py "$data" --algo cdt --steps "$cdt_steps" --warmup 1 \
      --threads 1 | ms)
    torch_all=$(.venv-bench/bin/python bench/offline_step_torch.py "$data" --algo cdt --steps "$cdt_steps" \
      --warmup 1 --threads "$threads" | ms)
  else
    "$bin/dsrl-train" "$algo" --task OfflineCarRun-v0 --dataset "$data" --steps $((steps + 1)) --cost-threshold 10 \
      --out "$work" >&2
    policy=$work/$algo/threshold-10/policy.json
    torch1=$(torch_step "$algo" 1)
    torch_all=$(torch_step "$algo" "$threads")
  fi
  candle=$(python3 -c "import json; t=json.load(open('$policy'))['training']; print(1000*(t['seconds']-t['first_step_seconds'])/(t['steps']-1))")
  rows+=("$(python3 -c "print('| %s | %.1f | %.1f | %.1f | %.2f |' % ('$algo', $candle, $torch1, $torch_all, \
$candle / $torch1))")")
done
{
  echo "| algorithm | candle, 1 thread (ms/step) | PyTorch $torch_version, 1 thread (ms/step) | PyTorch $torch_version, $threads threads (ms/step) | candle / PyTorch 1 thread |"
  echo "|---|---|---|---|---|"
  printf '%s\n' "${rows[@]}"
  echo
  echo "CPU: $cpu ($threads cores), AVX-512: $avx512. $steps steps per run at batch 512 (CDT: $cdt_steps at batch 2048),"
  echo "OfflineCarRun-v0 starter;"
  echo "PyTorch after $warmup warm-up steps with batches built beforehand (OSRL osrl-lib 0.1.0); candle after its first"
  echo "step, its time including drawing its batches. Load average at start: $load."
} > bench/out/offline_step.md
cat bench/out/offline_step.md
