"""DSRL's `dsrl.infos`, for scripts that read the density presets from it (OSRL's training scripts do:
`DENSITY_CFG[task + "_density" + str(density)]` gives `cbins`, `rbins`, `max_npb` and `min_npb` for
`pre_process_data`). The presets are the server's own (`data/density_presets.csv`, compiled in)."""
import json

from . import _native

DENSITY_CFG = {
    f"{p['task']}_density{p['density']}": {k: p[k] for k in ("cbins", "rbins", "max_npb", "min_npb")}
    for p in json.loads(_native.density_presets_json())
}
