#!/usr/bin/env bash
# Regenerates filters/tests/it/golden/filters.json: the outputs of DSRL's own pre_process_data (0.1.0 from PyPI,
# patched to the current reference's bounds; see make_golden.py) on datasets dsrl-make-dataset writes.
# Needs network access to PyPI the first time (it builds .venv-golden). Not run by CI: the fixtures are committed.
set -euo pipefail
cd "$(dirname "$0")/../.."
tests/golden/reference-venv.sh
cargo build --release --bin dsrl-make-dataset
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
.venv-golden/bin/python tests/golden/make_golden.py \
  --make-dataset "${CARGO_TARGET_DIR:-target}/release/dsrl-make-dataset" \
  --work "$work" --out filters/tests/it/golden/filters.json
