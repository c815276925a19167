#!/usr/bin/env bash
# The project's tests, as CI runs them: system packages and the pinned Python test environment, formatting,
# the generated gRPC code's drift check (a test), clippy with warnings as errors, then every test of the
# workspace (unit, per-crate integration, cross-process end-to-end).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install-system-deps.sh --tests
scripts/setup-python.sh
# The simulators (Bullet-Safety-Gym, Safety-Gymnasium, MetaDrive) in .venv-sim, with all 38 tasks checked.
sim/setup.sh --check
# pyo3 (the simulator worker) builds against this interpreter; it must be the one .venv-sim was made from.
export PYO3_PYTHON="${PYO3_PYTHON:-$(command -v "${PYTHON:-python3}")}"
cargo fmt --all -- --check
cargo clippy --locked --workspace --all-targets -- -D warnings
cargo test --locked --workspace
