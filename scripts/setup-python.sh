#!/usr/bin/env bash
# Creates the pinned Python environment the tests use (.venv at the repository root) from nothing.
# Idempotent: re-running only installs what tests/python/requirements*.txt add or change.
set -euo pipefail
cd "$(dirname "$0")/.."
python=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$python" -m venv .venv
fi
stamp=.venv/.requirements.sha256
want=$(cat tests/python/requirements.txt tests/python/requirements-nodeps.txt | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "setting up the test Python environment (.venv) from tests/python/requirements*.txt" >&2
  .venv/bin/python -m pip install --quiet --disable-pip-version-check -r tests/python/requirements.txt
  .venv/bin/python -m pip install --quiet --disable-pip-version-check --no-deps -r tests/python/requirements-nodeps.txt
  echo "$want" > "$stamp"
fi
