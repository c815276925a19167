#!/usr/bin/env bash
# Benchmark: one BC training step (batch 512, MLP [obs, 256, 256, act], MSE, Adam) in candle (`dsrl-train bc`,
# release build, one thread) vs the same update by hand in NumPy/OpenBLAS (bench/bc_step_reference.py, a stand-in for
# PyTorch on CPU, which cannot be installed here), on the same data: the committed OfflineCarRun-v0 starter.
# Prints a Markdown table (also written to bench/out/bc_step.md). Usage: bench/bc_step.sh [STEPS=3000]
set -euo pipefail
cd "$(dirname "$0")/.."
steps=${1:-3000}
scripts/setup-python.sh >&2
export PYO3_PYTHON="${PYO3_PYTHON:-$(command -v "${PYTHON:-python3}")}"
cargo build --release --locked -p dsrl-train --bins >&2
bin=${CARGO_TARGET_DIR:-target}/release
data=$(ls data/starter/OfflineCarRun-v0/*.parquet)
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-bc-bench.XXXXXX")
trap 'rm -rf "$work"' EXIT
mkdir -p bench/out
"$bin/dsrl-train" bc --task OfflineCarRun-v0 --mode all --dataset "$data" --steps "$steps" --out "$work" >&2
candle=$(python3 -c "import json; t=json.load(open('$work/bc-all/policy.json'))['training']; print(1000*t['seconds']/t['steps'])")
numpy=$(OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bc_step_reference.py "$data" --steps "$steps" | python3 -c "import json,sys; print(json.load(sys.stdin)['ms_per_step'])")
numpy_mt=$(.venv/bin/python bench/bc_step_reference.py "$data" --steps "$steps" | python3 -c "import json,sys; print(json.load(sys.stdin)['ms_per_step'])")
{
  echo "| implementation | ms per step (batch 512) |"
  echo "|---|---|"
  printf "| candle (dsrl-train bc, 1 thread) | %.2f |\n" "$candle"
  printf "| NumPy/OpenBLAS by hand, 1 thread | %.2f |\n" "$numpy"
  printf "| NumPy/OpenBLAS by hand, all cores | %.2f |\n" "$numpy_mt"
} > bench/out/bc_step.md
cat bench/out/bc_step.md
