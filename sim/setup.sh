#!/usr/bin/env bash
# Creates the pinned simulator environment (.venv-sim at the repository root) from nothing, applies the fixes the
# simulators need here (sim/python/apply_fixes.py), and checks that all 38 tasks build, reset and step.
# Idempotent: a re-run with unchanged requirements only repeats the check (pass --no-check to skip it).
set -euo pipefail
cd "$(dirname "$0")/.."
python=${PYTHON:-python3}
venv=.venv-sim
if [ ! -x "$venv/bin/python" ]; then
  "$python" -m venv "$venv"
fi
stamp="$venv/.requirements.sha256"
want=$(cat sim/python/requirements.txt sim/python/constraints.txt sim/python/apply_fixes.py | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  pip=("$venv/bin/python" -m pip install --quiet --disable-pip-version-check)
  "${pip[@]}" -c sim/python/constraints.txt -r sim/python/requirements.txt
  # safety-gymnasium pins pygame==2.1.0 (no Python 3.11 wheel) and never imports it.
  "${pip[@]}" --no-deps safety-gymnasium==1.0.0
  PYTHONWARNINGS=ignore "$venv/bin/python" sim/python/apply_fixes.py
  echo "$want" > "$stamp"
fi
if [ "${1:-}" != "--no-check" ]; then
  PYTHONWARNINGS=ignore "$venv/bin/python" sim/python/check_tasks.py data/tasks.csv 2>&1 \
    | grep -v -e "^pybullet build time" -e "AdroitHand" -e "device(error)" >&2
fi
