"""DSRL 0.1.0 on a full-size file, as a user runs it: `get_dataset(h5path)` (h5py reads every key into NumPy) then
`pre_process_data` with one filter; prints JSON with the seconds of each and the process's peak resident memory.

usage: scale_reference.py FILE.hdf5 FILTER   (FILTER: noise=0.1 or density=0.5)
"""

import contextlib
import io
import json
import random
import resource
import sys
import time
import types

import gymnasium
import numpy as np

# pre_process_data draws a matplotlib figure; its time is not what is compared here.
stub = types.ModuleType("matplotlib.pyplot")
stub.__getattr__ = lambda name: (lambda *a, **k: None)
sys.modules["matplotlib.pyplot"] = stub

import dsrl.offline_env as reference  # noqa: E402

# OfflineCarPush2Gymnasium-v0's normalization constants (data/tasks.csv) and DSRL's density preset for it.
CONSTANTS = dict(max_episode_reward=15.141648491514314, min_episode_reward=0.00029391133526335267,
                 max_episode_cost=250.0, min_episode_cost=0.0)
FILTERS = {
    "noise=0.1": dict(outliers_percent=0.1),
    "density=0.5": dict(density=0.5, cbins=10, rbins=8, max_npb=50, min_npb=2),
}


def main():
    path, name = sys.argv[1], sys.argv[2]
    env = reference.OfflineEnv(**CONSTANTS)
    # DSRL wraps the task's own environment, whose spaces get_dataset checks the file against; CarPush2's, without
    # building the simulator (its shapes, not its bounds, are what is checked).
    env.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (88,), np.float32)
    env.action_space = gymnasium.spaces.Box(-1.0, 1.0, (2,), np.float32)
    env.set_target_cost(20)
    random.seed(0)
    start = time.perf_counter()
    data = env.get_dataset(h5path=path)
    loaded = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        env.pre_process_data(data, **FILTERS[name])
    done = time.perf_counter()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(json.dumps({"filter": name, "load_seconds": loaded - start, "filter_seconds": done - loaded,
                      "seconds": done - start, "peak_rss_bytes": peak}))


if __name__ == "__main__":
    main()
