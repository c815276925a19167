#!/usr/bin/env bash
# Runs tests/parity/osrl_export_check.py: README's PyTorch export snippet on OSRL's own modules (osrl-lib 0.1.0 from
# PyPI, installed without its training dependencies) in .venv-bench (PyTorch; made on first use, ~5 GB: see
# bench/requirements-torch.txt). Not part of scripts/test.sh for that reason.
set -euo pipefail
cd "$(dirname "$0")/../.."
if [ ! -x .venv-bench/bin/python ]; then
  python3 -m venv .venv-bench
  .venv-bench/bin/pip install -q -r bench/requirements-torch.txt >&2
fi
.venv-bench/bin/pip install -q safetensors==0.8.0 >&2
.venv-bench/bin/pip install -q --no-deps osrl-lib==0.1.0 >&2
exec .venv-bench/bin/python tests/parity/osrl_export_check.py
