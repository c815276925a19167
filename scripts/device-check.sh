#!/usr/bin/env bash
# The GPU checks of `dsrl-train --device cuda`, run on a machine with a GPU (not in CI): the binary from
# scripts/build-cuda.sh, PyTorch with CUDA and pyarrow already installed there (no package registry needed).
#   1. Parity: BC trained 200 steps from the same seed on the CPU and on the GPU; every weight of the two
#      checkpoints within float tolerance (the first weights are the same; only rounding differs).
#   2. Speed: one BC step at OSRL's batch (512) on the GPU, candle against OSRL's code path in PyTorch
#      (bench/bc_step_torch.py --device cuda), on the committed OfflineCarRun-v0 starter, in one run.
# Writes a Markdown table to $OUT/device-check.md (or ./device-check.md) with the GPU's name and the date.
# Usage: scripts/device-check.sh PATH/TO/cuda/dsrl-train [STEPS=3000]
set -euo pipefail
cd "$(dirname "$0")/.."
train=${1:?the dsrl-train built by scripts/build-cuda.sh}
steps=${2:-3000}
out=${OUT:-.}/device-check.md
python=${PYTHON:-python3}
data=$(ls data/starter/OfflineCarRun-v0/*.parquet)
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-device-check.XXXXXX")
trap 'rm -rf "$work"' EXIT
gpu=$(nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | head -1)

echo "parity: BC 200 steps on cpu and cuda" >&2
for device in cpu cuda; do
  "$train" bc --task OfflineCarRun-v0 --mode all --dataset "$data" --steps 200 --device "$device" \
    --out "$work/$device" >&2
done
parity=$("$python" - "$work/cpu/bc-all/policy.safetensors" "$work/cuda/bc-all/policy.safetensors" <<'PY'
import json, struct, sys
import numpy as np
def read(path):
    raw = open(path, "rb").read()
    n = struct.unpack("<Q", raw[:8])[0]
    header = json.loads(raw[8:8 + n])
    return {k: np.frombuffer(raw[8 + n + v["data_offsets"][0]:8 + n + v["data_offsets"][1]], np.float32)
            for k, v in header.items() if k != "__metadata__"}
a, b = read(sys.argv[1]), read(sys.argv[2])
assert a.keys() == b.keys(), (a.keys(), b.keys())
worst = max(float(np.max(np.abs(a[k] - b[k]) / (1 + np.abs(a[k])))) for k in a)
print(f"{worst:.2e}")
sys.exit(0 if worst < 1e-3 else 1)
PY
) || { echo "parity failed: largest relative weight difference $parity" >&2; status=1; }

echo "speed: $steps BC steps on the GPU, candle and PyTorch" >&2
"$train" bc --task OfflineCarRun-v0 --mode all --dataset "$data" --steps "$steps" --device cuda --out "$work/speed" >&2
candle=$("$python" -c "import json; t=json.load(open('$work/speed/bc-all/policy.json'))['training']; print(1000*t['seconds']/t['steps'])")
torch=$("$python" bench/bc_step_torch.py "$data" --steps "$steps" --device cuda | "$python" -c 'import json,sys; print(json.load(sys.stdin)["ms_per_step"])')
torch_version=$("$python" -c "import torch; print(torch.__version__)")
{
  echo "GPU: $gpu; $(date -u +%F); dsrl-train $("$train" --version | cut -d' ' -f2) (cuda), commit $(git rev-parse --short=12 HEAD 2>/dev/null || echo unknown)."
  echo
  echo "| check | result |"
  echo "|---|---|"
  echo "| BC, 200 steps, cpu vs cuda: largest relative weight difference | $parity |"
  printf "| BC step, batch 512, candle on cuda (ms) | %.3f |\n" "$candle"
  printf "| BC step, batch 512, PyTorch %s on cuda (ms) | %.3f |\n" "$torch_version" "$torch"
} > "$out"
cat "$out"
exit "${status:-0}"
