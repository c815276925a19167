#!/usr/bin/env bash
# The GPU checks of `dsrl-train --device cuda`, run on a machine with a GPU (not in CI): the binary from
# scripts/build-cuda.sh, PyTorch with CUDA, NumPy and pyarrow already installed there. That machine reaches no
# package registry: OSRL and what its step imports come as wheels made here by `scripts/device-check.sh --wheels DIR`
# (carried with the run; without them only candle's columns are filled).
#   1. Parity of one training step, CPU against GPU, for each method (BC, BCQ-Lag, BEAR-Lag, CPQ, COptiDICE, CDT,
#      CAPS), from the same seed on the committed OfflineCarRun-v0 starter: the step's losses (the training record's
#      `final`, computed from the same initial weights on the same batch) within 1e-4 relative, and every updated
#      weight within 2·lr + 1e-5 of the CPU's (Adam's first step moves each weight by ±lr, so a gradient whose
#      sign rounds the other way on the GPU may land 2·lr apart; anything wider is a wrong gradient).
#   2. Speed: per method, one training step at OSRL's batch (512; CDT 2048) on the GPU, candle (dsrl-train's own
#      timer after its first step) against OSRL's own code in PyTorch on the same GPU (bench/bc_step_torch.py for
#      BC, bench/offline_step_torch.py for the rest; CAPS has no OSRL implementation), in one run; and OSRL's full
#      budget for one task per method projected from the measured step (steps × models × ms/step; not a run).
# Writes a Markdown table to $OUT/device-check.md (or ./device-check.md) with the GPU's name and the date.
# Usage: scripts/device-check.sh PATH/TO/cuda/dsrl-train [STEPS=200] [WHEELS_DIR]
#        scripts/device-check.sh --wheels DIR     (here, with a registry: download the wheels to carry)
set -euo pipefail
cd "$(dirname "$0")/.."
if [ "${1:-}" = --wheels ]; then
  dir=${2:?a folder for the wheels}
  mkdir -p "$dir"
  # What `import osrl.algorithms` needs besides torch, numpy and pyarrow (bench/requirements-torch.txt), and OSRL
  # itself without its own pins (they ask for torch 1.13 and simulators the step never touches).
  grep -v -E '^(#|torch==|numpy==|pyarrow==|$)' bench/requirements-torch.txt > "$dir/requirements.txt"
  echo "downloading $(wc -l < "$dir/requirements.txt") wheels and OSRL's two into $dir" >&2
  # Binary wheels for the device's Python (DEVICE_PYTHON, default 3.12: scipy and PyYAML are built per version).
  python3 -m pip download -q --only-binary=:all: --python-version "${DEVICE_PYTHON:-3.12}" \
    --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_28_x86_64 --no-deps -d "$dir" -r "$dir/requirements.txt"
  python3 -m pip download -q --no-deps -d "$dir" osrl-lib==0.1.0 fast-safe-rl==0.1.0
  exit 0
fi
train=${1:?the dsrl-train built by scripts/build-cuda.sh}
steps=${2:-200}
wheels=${3:-}
out=${OUT:-.}/device-check.md
python=${PYTHON:-python3}
data=$(ls data/starter/OfflineCarRun-v0/*.parquet)
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-device-check.XXXXXX")
trap 'rm -rf "$work"' EXIT
gpu=$(nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | head -1)
torch_ok=0
if [ -n "$wheels" ]; then
  echo "installing OSRL from $wheels" >&2
  "$python" -m pip install -q --no-index --no-deps --target "$work/py" "$wheels"/*.whl
  export PYTHONPATH="$work/py${PYTHONPATH:+:$PYTHONPATH}"
fi
"$python" -c "import osrl.algorithms" 2>/dev/null && torch_ok=1

# method | dsrl-train arguments | checkpoint folder | OSRL steps | models | PyTorch reference
methods=(
  "bc|bc --mode all|bc-all|100000|1|bc"
  "bcql|bcql --cost-threshold 10|bcql/threshold-10|100000|3|bcql"
  "bearl|bearl --cost-threshold 10|bearl/threshold-10|300000|3|bearl"
  "cpq|cpq --cost-threshold 10|cpq/threshold-10|100000|3|cpq"
  "coptidice|coptidice --cost-threshold 10|coptidice/threshold-10|100000|3|coptidice"
  "cdt|cdt|cdt|100000|1|cdt"
  "caps|caps|caps|100000|1|"
)
rows=()
status=0
for line in "${methods[@]}"; do
  IFS='|' read -r method cmd folder osrl_steps models reference <<< "$line"
  echo "== $method: parity (1 step, cpu and cuda)" >&2
  for device in cpu cuda; do
    # shellcheck disable=SC2086  # cmd holds the method and its own options
    RAYON_NUM_THREADS=$(nproc) "$train" $cmd --task OfflineCarRun-v0 --dataset "$data" --steps 1 \
      --device "$device" --out "$work/$method-$device" >&2
  done
  parity=$("$python" - "$work/$method-cpu/$folder" "$work/$method-cuda/$folder" <<'PY'
import json, re, struct, sys
import numpy as np
def read(folder):
    raw = open(f"{folder}/policy.safetensors", "rb").read()
    n = struct.unpack("<Q", raw[:8])[0]
    header = json.loads(raw[8:8 + n])
    weights = {k: np.frombuffer(raw[8 + n + v["data_offsets"][0]:8 + n + v["data_offsets"][1]], np.float32)
               for k, v in header.items() if k != "__metadata__"}
    return weights, json.load(open(f"{folder}/policy.json"))["training"]
(a, ta), (b, tb) = read(sys.argv[1]), read(sys.argv[2])
assert a.keys() == b.keys(), (a.keys(), b.keys())
assert tb["device"].startswith("cuda"), tb["device"]
losses = ta.get("final") or {"mse": ta["final_mse"]}
other = tb.get("final") or {"mse": tb["final_mse"]}
loss_gap = max(abs(losses[k] - other[k]) / max(1e-6, abs(losses[k])) for k in losses)
# The largest learning rate among the method's settings bounds how far one Adam step moves a weight.
lrs = [float(x) for x in re.findall(r"lr: ([0-9.e-]+)", str(ta.get("settings", "")))] or [float(ta.get("lr", 1e-3))]
bound = 2 * max(lrs) + 1e-5
weight_gap = max(float(np.max(np.abs(a[k] - b[k]) - 1e-5 * np.abs(a[k]))) for k in a)
ok = loss_gap < 1e-4 and weight_gap <= bound
print(f"{'pass' if ok else 'FAIL'}: losses {loss_gap:.1e}, weights {weight_gap:.1e} (bound {bound:.0e})")
sys.exit(0 if ok else 1)
PY
) || status=1
  echo "== $method: speed ($steps steps on the GPU, candle then PyTorch)" >&2
  "$train" $cmd --task OfflineCarRun-v0 --dataset "$data" --steps $((steps + 1)) --device cuda \
    --out "$work/$method-speed" >&2
  candle=$("$python" -c "import json; t=json.load(open('$work/$method-speed/$folder/policy.json'))['training']; \
print(1000*(t['seconds']-t['first_step_seconds'])/(t['steps']-1))")
  torch=n/a
  if [ "$reference" = bc ]; then
    torch=$("$python" bench/bc_step_torch.py "$data" --steps "$steps" --device cuda \
      | "$python" -c 'import json,sys; print("%.3f" % json.load(sys.stdin)["ms_per_step"])')
  elif [ -n "$reference" ] && [ "$torch_ok" = 1 ]; then
    torch=$("$python" bench/offline_step_torch.py "$data" --algo "$reference" --steps "$steps" --device cuda \
      | "$python" -c 'import json,sys; print("%.3f" % json.loads(sys.stdin.read().strip().splitlines()[-1])["ms_per_step"])')
  fi
  hours=$("$python" -c "print('%.1f' % ($candle * $osrl_steps * $models / 3.6e6))")
  rows+=("| $method | $parity | $(printf %.3f "$candle") | $torch | $osrl_steps × $models | $hours |")
done
torch_version=$("$python" -c "import torch; print(torch.__version__)")
{
  echo "GPU: $gpu; $(date -u +%F); dsrl-train $("$train" --version | cut -d' ' -f2) (cuda), commit $(git rev-parse --short=12 HEAD 2>/dev/null || echo unknown); PyTorch $torch_version."
  echo
  echo "| method | one step, cpu vs cuda | candle on cuda (ms/step) | OSRL on PyTorch, cuda (ms/step) | OSRL's budget (steps × models) | projected GPU hours for it |"
  echo "|---|---|---|---|---|---|"
  printf '%s\n' "${rows[@]}"
  echo
  echo "Batch: OSRL's (512; CDT 2048), OfflineCarRun-v0 starter, $steps timed steps after one untimed. The hours are the"
  echo "measured step time times OSRL's steps, not a run of the full budget."
} > "$out"
cat "$out"
exit "$status"
