#!/usr/bin/env bash
# Creates the pinned simulator environment (.venv-sim at the repository root) from nothing, applies the fixes the
# simulators need here (sim/python/apply_fixes.py), and checks that all 38 tasks build, reset and step.
# Idempotent: a re-run with unchanged requirements and fixes does nothing unless --check asks to repeat the task
# check (CI passes it); --no-check skips the check even after a (re)build.
set -euo pipefail
cd "$(dirname "$0")/.."
python=${PYTHON:-python3}
venv=.venv-sim
if [ ! -x "$venv/bin/python" ]; then
  "$python" -m venv "$venv"
fi
stamp="$venv/.requirements.sha256"
want=$(cat sim/python/requirements.txt sim/python/constraints.txt sim/python/apply_fixes.py | sha256sum | cut -d' ' -f1)
mode=${1:-}
check=no
[ "$mode" = "--check" ] && check=yes
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  check=yes
  pip=("$venv/bin/python" -m pip install --quiet --disable-pip-version-check)
  "${pip[@]}" -c sim/python/constraints.txt -r sim/python/requirements.txt
  # safety-gymnasium pins pygame==2.1.0 (no Python 3.11 wheel) and never imports it.
  "${pip[@]}" --no-deps safety-gymnasium==1.0.0
  PYTHONWARNINGS=ignore "$venv/bin/python" sim/python/apply_fixes.py
fi
if [ "$check" = yes ] && [ "$mode" != "--no-check" ]; then
  PYTHONWARNINGS=ignore "$venv/bin/python" sim/python/check_tasks.py data/tasks.csv 2>&1 \
    | grep -v -e "^pybullet build time" -e "AdroitHand" -e "device(error)" >&2
fi
# Written last: an install or check that failed is redone next time.
echo "$want" > "$stamp"
