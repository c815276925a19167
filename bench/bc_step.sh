#!/usr/bin/env bash
# Benchmark: one BC training step (OSRL's BC: batch 512, MLP [obs, 256, 256, act], MSE, Adam) side by side in one
# run, on the same data (the committed OfflineCarRun-v0 starter):
#   - candle: `dsrl-train bc` (release build, one thread, the learner's own timer over all steps);
#   - PyTorch on CPU (bench/bc_step_torch.py: OSRL's code path, torch.optim.Adam), one thread and all cores;
#   - NumPy/OpenBLAS by hand (bench/bc_step_reference.py), one thread, for scale.
# PyTorch lives in its own environment, .venv-bench (bench/requirements-torch.txt; the PyPI wheel pulls ~5 GB of
# CUDA libraries that it loads at import even on a CPU-only machine), made on first use. Prints a Markdown table
# (also bench/out/bc_step.md, and into BENCHMARKS.md at 3000 steps) with the CPU, whether it has AVX-512, the build's
# commit and the load average when the run started (other work on the machine slows every column).
# Usage: bench/bc_step.sh [STEPS=3000]   SKIP_BUILD=1 uses the dsrl-train already built instead of running cargo.
set -euo pipefail
cd "$(dirname "$0")/.."
steps=${1:-3000}
scripts/setup-python.sh >&2
if [ ! -x .venv-bench/bin/python ]; then
  python3 -m venv .venv-bench
  .venv-bench/bin/pip install -q -r bench/requirements-torch.txt >&2
fi
if [ "${SKIP_BUILD:-0}" != 1 ]; then
  export PYO3_PYTHON="${PYO3_PYTHON:-$(command -v "${PYTHON:-python3}")}"
  cargo build --release --locked -p dsrl-train --bins >&2
fi
bin=${CARGO_TARGET_DIR:-target}/release
data=$(ls data/starter/OfflineCarRun-v0/*.parquet)
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-bc-bench.XXXXXX")
trap 'rm -rf "$work"' EXIT
mkdir -p bench/out
source bench/lib.sh  # here: the load is read after the build
ms() { python3 -c "import json,sys; print(json.load(sys.stdin)['ms_per_step'])"; }
"$bin/dsrl-train" bc --task OfflineCarRun-v0 --mode all --dataset "$data" --steps "$steps" --out "$work" >&2
training() { python3 -c "import json; t=json.load(open('$work/bc-all/policy.json'))['training']; print($1)"; }
candle=$(training "1000*t['seconds']/t['steps']")
commit=$(training "t['code_commit']")
torch1=$(.venv-bench/bin/python bench/bc_step_torch.py "$data" --steps "$steps" --threads 1 | ms)
torch_all=$(.venv-bench/bin/python bench/bc_step_torch.py "$data" --steps "$steps" --threads "$(nproc)" | ms)
numpy=$(OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bc_step_reference.py "$data" --steps "$steps" | ms)
torch_version=$(.venv-bench/bin/python -c "import torch; print(torch.__version__)")
{
  echo "| implementation | ms per step (batch 512) |"
  echo "|---|---|"
  printf "| candle (dsrl-train bc, 1 thread) | %.2f |\n" "$candle"
  printf "| PyTorch %s on CPU, 1 thread | %.2f |\n" "$torch_version" "$torch1"
  printf "| PyTorch %s on CPU, %s threads | %.2f |\n" "$torch_version" "$(nproc)" "$torch_all"
  printf "| NumPy/OpenBLAS by hand, 1 thread | %.2f |\n" "$numpy"
  echo
  echo "candle: the dsrl-train of \`$commit\`. CPU: $(cpu_model) ($(nproc) cores), AVX-512: $(has_avx512). $steps steps, OfflineCarRun-v0"
  echo "starter. Load average at start: $bench_load. Measured $(date -u +%F)."
  echo
  python3 -c "r = $candle / $torch1; print('Goal (no slower than PyTorch on 1 thread): %s, candle / PyTorch 1 thread = %.2f.' % ('met' if r <= 1 else 'not met', r))"
} > bench/out/bc_step.md
cat bench/out/bc_step.md
# The table goes into BENCHMARKS.md between its markers (only from a run at the documented count of steps).
if [ "$steps" = 3000 ]; then
  bench_section bc_step.sh bench/out/bc_step.md
fi
