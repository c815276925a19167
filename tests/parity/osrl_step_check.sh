#!/usr/bin/env bash
# Runs tests/parity/osrl_step_check.py: one training step of each of dsrl-train's five offline baselines (BCQ-Lag,
# BEAR-Lag, CPQ, COptiDICE, CDT) against OSRL's own PyTorch code (osrl-lib 0.1.0 from PyPI) in .venv-bench, with the
# same weights, batch and random numbers. Not part of scripts/test.sh: PyTorch is ~5 GB (bench/requirements-torch.txt).
# Its last result is in README.md ("Held to OSRL's code, one step at a time").
#   tests/parity/osrl_step_check.sh [bcql bearl cpq coptidice cdt]
set -euo pipefail
cd "$(dirname "$0")/../.."
if [ ! -x .venv-bench/bin/python ]; then
  echo "creating .venv-bench (PyTorch on CPU, ~5 GB)" >&2
  python3 -m venv .venv-bench
  .venv-bench/bin/pip install -q -r bench/requirements-torch.txt >&2
fi
.venv-bench/bin/pip install -q safetensors==0.8.0 >&2
.venv-bench/bin/pip install -q --no-deps osrl-lib==0.1.0 fast-safe-rl==0.1.0 >&2
echo "building dsrl-train (release)" >&2
cargo build --release --locked -p dsrl-train >&2
exec .venv-bench/bin/python tests/parity/osrl_step_check.py "${CARGO_TARGET_DIR:-target}/release/dsrl-train" "$@"
