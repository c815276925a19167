"""Writes a DSRL-layout HDF5 file of CarPush2's shape at the paper's count: 4,407 trajectories of 1,000 steps, 88
observation and 2 action features, random float32 values (the data's content does not matter to loading and
filtering), rewards and costs shaped so DSRL's noise and density filters apply. Written in slices with h5py's gzip
(level 4, auto-chunked), as DSRL's process_dataset.py wrote its files (`compression='gzip'`, spec §1.3), so that
reading it costs what reading DSRL's own files costs.

usage: make_dsrl_scale.py OUT.hdf5 [EPISODES=4407]
"""

import sys

import h5py
import numpy as np

out = sys.argv[1]
episodes = int(sys.argv[2]) if len(sys.argv) > 2 else 4407
length, obs_dim, act_dim = 1000, 88, 2
rows = episodes * length
rng = np.random.default_rng(4407)
# Per episode: a cost return spread over 0..250 and a reward return that rises with it (DSRL's tempting corner is
# populated), each spread evenly over the episode's steps.
cost_returns = rng.uniform(0, 250, episodes)
reward_returns = 2 + 12 * cost_returns / 250 + rng.uniform(-1, 1, episodes)
with h5py.File(out, "w") as f:
    keys = {
        "observations": (obs_dim, np.float32),
        "next_observations": (obs_dim, np.float32),
        "actions": (act_dim, np.float32),
    }
    data = {k: f.create_dataset(k, (rows, d), dtype=t, compression="gzip") for k, (d, t) in keys.items()}
    rewards = f.create_dataset("rewards", (rows,), dtype=np.float32, compression="gzip")
    costs = f.create_dataset("costs", (rows,), dtype=np.float32, compression="gzip")
    terminals = f.create_dataset("terminals", (rows,), dtype=bool, compression="gzip")
    timeouts = f.create_dataset("timeouts", (rows,), dtype=bool, compression="gzip")
    block = 100
    for e0 in range(0, episodes, block):
        e1 = min(episodes, e0 + block)
        a, b = e0 * length, e1 * length
        n = b - a
        for k, (d, _) in keys.items():
            data[k][a:b] = rng.standard_normal((n, d), dtype=np.float32)
        rewards[a:b] = np.repeat(reward_returns[e0:e1] / length, length).astype(np.float32)
        costs[a:b] = np.repeat(cost_returns[e0:e1] / length, length).astype(np.float32)
        t = np.zeros(n, dtype=bool)
        t[length - 1 :: length] = True
        terminals[a:b] = np.zeros(n, dtype=bool)
        timeouts[a:b] = t
print(f"{out}: {episodes} trajectories, {rows} transitions", file=sys.stderr)
