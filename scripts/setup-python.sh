#!/usr/bin/env bash
# Creates the pinned Python environments the tests use from nothing: .venv (tests/python/requirements*.txt) and
# .venv-numpy2 (tests/python/requirements-numpy2.txt: the Python package under NumPy 2.x).
# Idempotent: re-running only installs what those files add or change.
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
if [ ! -x .venv-numpy2/bin/python ]; then
  "$python" -m venv .venv-numpy2
fi
stamp=.venv-numpy2/.requirements.sha256
want=$(sha256sum < tests/python/requirements-numpy2.txt | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "setting up .venv-numpy2 from tests/python/requirements-numpy2.txt" >&2
  .venv-numpy2/bin/python -m pip install --quiet --disable-pip-version-check -r tests/python/requirements-numpy2.txt
  echo "$want" > "$stamp"
fi
