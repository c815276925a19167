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
# Prints a Markdown table (also bench/out/offline_step.md, and into BENCHMARKS.md at 50 steps) with the CPU, whether
# it has AVX-512 and the load average when the run started (other work on the machine slows every column).
# Usage: bench/offline_step.sh [STEPS=50]
# SKIP_BUILD=1 uses the dsrl-train already built instead of running cargo. BEFORE=<a dsrl-train> adds its column beside
# the build's, in the same run (a change's before and after), with BEFORE_LABEL naming it (e.g. its commit).
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
source bench/lib.sh  # here: the load is read after the build
torch_version=$(.venv-bench/bin/python -c "import torch; print(torch.__version__)")
ms() { python3 -c "import json,sys; print(json.loads(sys.stdin.read().strip().splitlines()[-1])['ms_per_step'])"; }
# ms a step of OSRL's code on $1 threads, for ${torch_args[@]} (algorithm, steps, warm-up, ...).
torch_step() { .venv-bench/bin/python bench/offline_step_torch.py "$data" "${torch_args[@]}" --threads "$1" | ms; }
rows=()
cdt_steps=${CDT_STEPS:-3}
# ms a step of the dsrl-train $1 on ${args[@]} (into $2), from its own timer, its first step left out.
candle_step() {
  "$1" "${args[@]}" --out "$2" >&2
  python3 -c "import json; t=json.load(open('$2/$policy'))['training']; print(1000*(t['seconds']-t['first_step_seconds'])/(t['steps']-1))"
}
cdt_small_steps=${CDT_SMALL_STEPS:-10}
# CDT twice: at OSRL's batch 2048, where a step's time varies by tens of percent from run to run (its 40-170 MB
# tensors), and at the sweep's batch 512, steadier.
for algo in bcql bearl cpq coptidice cdt cdt-512; do
  echo "== $algo" >&2
  if [ "$algo" = cdt ] || [ "$algo" = cdt-512 ]; then
    # CDT is trained once (no threshold) and takes seconds a step: fewer steps, one warm-up.
    if [ "$algo" = cdt ]; then batch=2048 n=$cdt_steps; else batch=512 n=$cdt_small_steps; fi
    label="cdt (batch $batch)"
    args=(cdt --task OfflineCarRun-v0 --dataset "$data" --steps $((n + 1)) --batch-size "$batch")
    policy=cdt/policy.json
    torch_args=(--algo cdt --steps "$n" --warmup 1 --cdt-batch "$batch")
  else
    args=("$algo" --task OfflineCarRun-v0 --dataset "$data" --steps $((steps + 1)) --cost-threshold 10)
    policy=$algo/threshold-10/policy.json
    label=$algo
    torch_args=(--algo "$algo" --steps "$steps" --warmup "$warmup")
  fi
  torch1=$(torch_step 1)
  torch_all=$(torch_step "$threads")
  candle=$(candle_step "$bin/dsrl-train" "$work/new-$algo")
  before=None
  [ -z "${BEFORE:-}" ] || before=$(candle_step "$BEFORE" "$work/before-$algo")
  rows+=("$(python3 -c "b = $before; print('| %s | %.1f |%s %.1f | %.1f | %.2f |' % ('$label', $candle, \
'' if b is None else ' %.1f |' % b, $torch1, $torch_all, $candle / $torch1))")")
done
{
  if [ -n "${BEFORE:-}" ]; then
    echo "| algorithm | candle, 1 thread (ms/step) | candle before (${BEFORE_LABEL:-BEFORE}), 1 thread (ms/step) | PyTorch $torch_version, 1 thread (ms/step) | PyTorch $torch_version, $threads threads (ms/step) | candle / PyTorch 1 thread |"
    echo "|---|---|---|---|---|---|"
  else
    echo "| algorithm | candle, 1 thread (ms/step) | PyTorch $torch_version, 1 thread (ms/step) | PyTorch $torch_version, $threads threads (ms/step) | candle / PyTorch 1 thread |"
    echo "|---|---|---|---|---|"
  fi
  printf '%s\n' "${rows[@]}"
  echo
  echo "candle: the dsrl-train of \`$(python3 -c "import json; print(json.load(open('$work/new-$algo/$policy'))['training']['code_commit'])")\`."
  echo "CPU: $(cpu_model) ($threads cores), AVX-512: $(has_avx512). $steps steps per run at batch 512 (CDT: $cdt_steps at batch 2048,"
  echo "$cdt_small_steps at batch 512),"
  echo "OfflineCarRun-v0 starter;"
  echo "PyTorch after $warmup warm-up steps with batches built beforehand (OSRL osrl-lib 0.1.0); candle after its first"
  echo "step, its time including drawing its batches. Load average at start: $bench_load. Measured $(date -u +%F)."
} > bench/out/offline_step.md
cat bench/out/offline_step.md
# The table goes into BENCHMARKS.md between its markers (only from a run at the documented count of steps).
if [ "$steps" = 50 ] && [ "$cdt_steps" = 3 ] && [ "$cdt_small_steps" = 10 ]; then
  bench_section offline_step.sh bench/out/offline_step.md
fi
