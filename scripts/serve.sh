#!/usr/bin/env bash
# Set-up and start on a fresh machine: installs the system packages and the simulator environment (sim/setup.sh),
# builds the release binaries, puts dsrl-server, dsrl-evaluator, dsrl-client, dsrl-sim-worker, dsrl-admin and
# dsrl-train on PATH (~/.cargo/bin), and starts the server on the embedded defaults: SQLite and a local object store under
# ~/.dsrl/server, the catalog compiled from data/tasks.csv, the starter datasets under data/starter, two local
# simulator workers, listening on 127.0.0.1:7070. Extra arguments go to dsrl-server (see --help).
set -euo pipefail
cd "$(dirname "$0")/.."
command -v cargo >/dev/null || { echo "cargo is required (https://rustup.rs)" >&2; exit 1; }
scripts/install-system-deps.sh
# The simulators for the local worker pool (.venv-sim); checks all 38 tasks the first time.
sim/setup.sh
export PYO3_PYTHON="${PYO3_PYTHON:-$(command -v "${PYTHON:-python3}")}"
cargo build --release --locked --workspace --bins
target=${CARGO_TARGET_DIR:-target}
bin_dir="${CARGO_HOME:-$HOME/.cargo}/bin"
mkdir -p "$bin_dir"
for b in dsrl-server dsrl-evaluator dsrl-client dsrl-sim-worker dsrl-admin dsrl-train; do
  ln -sf "$(realpath "$target/release/$b")" "$bin_dir/$b"
done
echo "dsrl-server, dsrl-evaluator, dsrl-client, dsrl-sim-worker, dsrl-admin and dsrl-train are linked into $bin_dir" >&2
exec "$target/release/dsrl-server" "$@"
