#!/usr/bin/env bash
# The Python package on every CPython from 3.9 to 3.12 this machine has (pyenv's or on PATH), with NumPy 1.x on the
# oldest and NumPy 2.x on the newest: one abi3 wheel built once, installed in a fresh venv per interpreter, then
# imported and used without a server (the catalog, DSRL's density presets, a committed starter read into DSRL's
# arrays). CI covers CPython 3.11 with NumPy 1.x and 2.x against a real server (tests/e2e/python_package.rs); this
# checks the other interpreters the package claims, out of CI because each needs its own venv and NumPy.
#   tests/parity/python_versions.sh            (state under ${DSRL_PY_CHECK_DIR:-~/.dsrl/python-versions})
set -euo pipefail
cd "$(dirname "$0")/../.."
state=${DSRL_PY_CHECK_DIR:-$HOME/.dsrl/python-versions}
mkdir -p "$state"
say() { echo "python-versions: $*" >&2; }
find_python() {
  local v=$1
  command -v "python$v" >/dev/null 2>&1 && PYENV_VERSION=$(pyenv versions --bare 2>/dev/null | grep "^$v\." | tail -1) \
    "python$v" -c "import sys; print(sys.executable)" 2>/dev/null
}
say "building the wheel once (maturin, abi3 for CPython >= 3.9)"
rm -rf "$state/wheel"
PYO3_PYTHON=${PYO3_PYTHON:-$(command -v python3)} python3 -m pip wheel --quiet --no-deps -w "$state/wheel" ./client/python
wheel=$(ls "$state/wheel"/dsrl_client-*.whl)
starter=$(ls data/starter/OfflineBallRun-v0/*.parquet | head -1)
results=()
for spec in "3.9 numpy<2" "3.10 numpy<2" "3.12 numpy>=2"; do
  v=${spec%% *}
  numpy=${spec#* }
  py=$(find_python "$v" || true)
  if [ -z "$py" ]; then
    say "CPython $v: not on this machine, skipped"
    results+=("{\"python\": \"$v\", \"checked\": false}")
    continue
  fi
  venv=$state/venv-$v
  [ -x "$venv/bin/python" ] || "$py" -m venv "$venv"
  say "CPython $v ($py) with $numpy"
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check "$numpy" "$wheel"
  results+=("$("$venv/bin/python" - "$starter" <<'PY'
import json, sys
import numpy as np
import dsrl_client
from dsrl_client.infos import DENSITY_CFG

data = dsrl_client.read_parquet(sys.argv[1])
keys = ["observations", "next_observations", "actions", "rewards", "costs", "terminals", "timeouts"]
assert set(keys) <= set(data), sorted(data)
n = len(data["rewards"])
assert data["observations"].shape == (n, dsrl_client.task("OfflineBallRun-v0")["obs_dim"])
assert data["observations"].dtype == np.float32 and data["terminals"].dtype == np.bool_
assert data["observations"].flags.writeable and int((data["terminals"] | data["timeouts"]).sum()) > 0
assert len(dsrl_client.tasks()) == 38 and "OfflineCarCircle-v0_density0.5" in DENSITY_CFG
print(json.dumps({"python": sys.version.split()[0], "numpy": np.__version__, "rows": n, "checked": True}))
PY
)")
done
printf '%s\n' "${results[@]}"
