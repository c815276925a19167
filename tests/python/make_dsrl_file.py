"""Writes a DSRL-layout HDF5 file (DSRL 0.1.0's keys, float32 arrays, bool flags) of `episodes` episodes of `length`
steps with `obs` observation and `act` action features: a stand-in for one of DSRL's released files, made by h5py as
DSRL's own files were.

Usage: make_dsrl_file.py PATH OBS ACT EPISODES LENGTH
"""

import sys

import h5py
import numpy as np

path, obs, act, episodes, length = sys.argv[1], *map(int, sys.argv[2:6])
n = episodes * length
rng = np.random.default_rng(episodes)
done = np.zeros(n, dtype=bool)
done[length - 1 :: length] = True
with h5py.File(path, "w") as f:
    f["observations"] = rng.standard_normal((n, obs)).astype(np.float32)
    f["next_observations"] = rng.standard_normal((n, obs)).astype(np.float32)
    f["actions"] = rng.uniform(-1, 1, (n, act)).astype(np.float32)
    f["rewards"] = rng.uniform(0, 1, n).astype(np.float32)
    f["costs"] = (rng.uniform(0, 1, n) < 0.1).astype(np.float32)
    f["terminals"] = np.zeros(n, dtype=bool)
    f["timeouts"] = done
