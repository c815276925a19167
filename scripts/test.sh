#!/usr/bin/env bash
# The project's tests, as CI runs them: system packages, then the pinned Python environments (the tests' and the
# simulators') installing in the background while Rust compiles (they wait on the network and pip, not on the cores
# the compiler needs; that all 38 tasks build, reset and step is sim/tests/it/all_tasks.rs), formatting, the
# generated gRPC code's drift check (a test), the test build with clippy's lints as errors, then every test of the
# workspace (unit, per-crate integration, cross-process end-to-end; scripts/run-tests.py).
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
# Clippy runs inside the test build, not before it: `cargo clippy` is `cargo check` with clippy-driver as the
# workspace's compiler wrapper, and a check pass shares nothing with the build that follows (a cold CI run spent
# ~8 minutes on it). Built through the same wrapper, every workspace crate is linted while it compiles, with the
# warnings made errors as `cargo clippy -- -D warnings` makes them; dependencies compile as they always do. The
# run below keeps the same environment, so it reuses these artifacts.
clippy_driver=$(rustup which clippy-driver 2>/dev/null || command -v clippy-driver || true)
[ -x "$clippy_driver" ] || { echo "clippy-driver not found: rustup component add clippy" >&2; exit 1; }
export RUSTC_WORKSPACE_WRAPPER=$clippy_driver
# How cargo-clippy hands clippy-driver its arguments (`cargo clippy -- -D warnings`).
export CLIPPY_ARGS="-D__CLIPPY_HACKERY__warnings__CLIPPY_HACKERY__"
# --all-targets: examples and every test target are linted, as `cargo clippy --all-targets` did.
cargo test --locked --workspace --all-targets --no-run
if ! wait "$setup_pid"; then
  cat "$setup_log" >&2
  echo "setting up the Python environments failed (above)" >&2
  exit 1
fi
cat "$setup_log" >&2
# Every test binary of the workspace, as `cargo test --locked --workspace --no-fail-fast` runs them (one failing
# binary does not hide the others' results), but the end-to-end binary beside the others instead of before them.
scripts/run-tests.py --locked
