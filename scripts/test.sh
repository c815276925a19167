#!/usr/bin/env bash
# The project's tests, as CI runs them: system packages, then the pinned Python environments (the tests' and the
# simulators') installing in the background while Rust compiles (they wait on the network and pip, not on the cores
# the compiler needs; that all 38 tasks build, reset and step is sim/tests/it/all_tasks.rs), formatting, the
# generated gRPC code's drift check (a test), clippy with warnings as errors, then every test of the workspace
# (unit, per-crate integration, cross-process end-to-end).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install-system-deps.sh --tests
setup_log=$(mktemp "${TMPDIR:-/tmp}/dsrl-setup.XXXXXX")
echo "setting up the Python environments in the background (.venv, .venv-numpy2, .venv-sim; log: $setup_log)" >&2
( scripts/setup-python.sh && sim/setup.sh --no-check ) > "$setup_log" 2>&1 &
setup_pid=$!
# pyo3 (the simulator worker) builds against this interpreter; it must be the one .venv-sim was made from.
export PYO3_PYTHON="${PYO3_PYTHON:-$(command -v "${PYTHON:-python3}")}"
cargo fmt --all -- --check
cargo clippy --locked --workspace --all-targets -- -D warnings
cargo test --locked --workspace --no-run
if ! wait "$setup_pid"; then
  cat "$setup_log" >&2
  echo "setting up the Python environments failed (above)" >&2
  exit 1
fi
cat "$setup_log" >&2
# --no-fail-fast: one failing test binary does not hide the results of the others.
cargo test --locked --workspace --no-fail-fast
