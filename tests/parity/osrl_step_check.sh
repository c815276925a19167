#!/usr/bin/env bash
# Runs tests/parity/osrl_step_check.py: one training step of each of dsrl-train's five offline baselines (BCQ-Lag,
# BEAR-Lag, CPQ, COptiDICE, CDT) against OSRL's own PyTorch code (osrl-lib 0.1.0 from PyPI) in .venv-bench, with the
# same weights, batch and random numbers. Not part of scripts/test.sh: PyTorch is ~5 GB (bench/requirements-torch.txt).
# A run of all five writes its table into README.md ("Held to OSRL's code, one step at a time") between its markers,
# with the dsrl-train sources' commit, PyTorch's version and the date.
#   tests/parity/osrl_step_check.sh [bcql bearl cpq coptidice cdt]   SKIP_BUILD=1 uses the dsrl-train already built.
set -euo pipefail
cd "$(dirname "$0")/../.."
if [ ! -x .venv-bench/bin/python ]; then
  echo "creating .venv-bench (PyTorch on CPU, ~5 GB)" >&2
  python3 -m venv .venv-bench
  .venv-bench/bin/pip install -q -r bench/requirements-torch.txt >&2
fi
.venv-bench/bin/pip install -q safetensors==0.8.0 >&2
.venv-bench/bin/pip install -q --no-deps osrl-lib==0.1.0 fast-safe-rl==0.1.0 >&2
if [ "${SKIP_BUILD:-0}" != 1 ]; then
  echo "building dsrl-train (release)" >&2
  export PYO3_PYTHON="${PYO3_PYTHON:-$(command -v "${PYTHON:-python3}")}"
  cargo build --release --locked -p dsrl-train >&2
fi
bin=${CARGO_TARGET_DIR:-target}/release/dsrl-train
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-parity.XXXXXX")
trap 'rm -rf "$work"' EXIT
# The last commit that changed what shapes dsrl-train's weights (train/build.rs's sources; its build records HEAD,
# which names the same code), "-modified" when the working tree differs there.
sources=(train/src policy/src suite/src Cargo.lock)
commit=$(git log -1 --format=%h -- "${sources[@]}")
git diff --quiet HEAD -- "${sources[@]}" || commit="$commit-modified"
.venv-bench/bin/python tests/parity/osrl_step_check.py "$bin" --table "$work/table.md" "$@"
if [ $# -eq 0 ]; then
  torch_version=$(.venv-bench/bin/python -c "import torch; print(torch.__version__)")
  {
    cat "$work/table.md"
    echo
    echo "dsrl-train of \`$commit\` against osrl-lib 0.1.0 on PyTorch $torch_version (CPU), seed 11. Measured $(date -u +%F)."
  } > "$work/section.md"
  python3 bench/into_benchmarks.py tests/parity/osrl_step_check.sh "$work/section.md" README.md
  echo "written into README.md" >&2
fi
