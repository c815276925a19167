#!/usr/bin/env bash
# Creates .venv-golden: DSRL 0.1.0 (the reference filters) on NumPy 1.24, for the golden fixtures and the filter
# benchmark. DSRL is installed without its dependencies: its simulator packages are not needed to filter arrays.
set -euo pipefail
cd "$(dirname "$0")/../.."
if [ ! -x .venv-golden/bin/python ]; then
  python3 -m venv .venv-golden
fi
.venv-golden/bin/python -m pip install --quiet --disable-pip-version-check -r tests/golden/requirements.txt
.venv-golden/bin/python -m pip install --quiet --disable-pip-version-check --no-deps dsrl==0.1.0
