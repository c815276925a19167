"""Times DSRL's pre_process_data (0.1.0, arrays already in memory) for the benchmark filters; prints JSON.

Each filter runs on a fresh OfflineEnv (as DSRL's generator state requires) after one warm-up call, `rounds`
times; reported: the median, as shipped (with its matplotlib figure saved as a PNG in the working directory) and
with plotting replaced by a no-op module.
usage: filter_reference.py DATA.parquet ROUNDS
"""
import contextlib
import io
import json
import os
import random
import statistics
import sys
import tempfile
import time
import types

import numpy as np
import pyarrow.parquet as pq

import dsrl.offline_env as reference

ANT_RUN = dict(max_episode_reward=955.4818725585938, min_episode_reward=0.001767391717990563,
               max_episode_cost=150.0, min_episode_cost=0.0)
FILTERS = {
    "density=0.5": dict(density=0.5, cbins=10, rbins=50, max_npb=6, min_npb=2),
    "noise=0.05": dict(outliers_percent=0.05),
    "obs_noise=0.1": dict(noise_scale=0.1),
    "discard=tempting": dict(inpaint_ranges=((0.5, 1.0, 0.5, 1.0),)),
    "epsilon=100": dict(epsilon=100.0),
}


def load(path):
    table = pq.read_table(path)
    data = {}
    for key, dim in [("observations", 33), ("next_observations", 33), ("actions", 8)]:
        data[key] = table.column(key).combine_chunks().flatten().to_numpy().astype(np.float32).reshape(-1, dim)
    for key in ["rewards", "costs"]:
        data[key] = table.column(key).to_numpy().astype(np.float32)
    for key in ["terminals", "timeouts"]:
        data[key] = table.column(key).to_numpy(zero_copy_only=False).astype(bool)
    return data


def run(data, kwargs):
    env = reference.OfflineEnv(**ANT_RUN)
    env.set_target_cost(10)
    random.seed(0)
    fresh = {k: v.copy() for k, v in data.items()}  # pre_process_data may modify its input; not timed
    start = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        env.pre_process_data(fresh, **kwargs)
    return time.perf_counter() - start


def main():
    data, rounds = load(sys.argv[1]), int(sys.argv[2])
    os.chdir(tempfile.mkdtemp())  # where the reference writes its PNGs
    result = {}
    for stubbed in [False, True]:
        if stubbed:
            # `import matplotlib.pyplot as plt` resolves through the package attribute once the package is
            # imported, so replace both.
            import matplotlib

            stub = types.ModuleType("matplotlib.pyplot")
            stub.__getattr__ = lambda name: (lambda *a, **k: None)
            sys.modules["matplotlib.pyplot"] = stub
            matplotlib.pyplot = stub
        for name, kwargs in FILTERS.items():
            run(data, kwargs)  # warm-up: imports, caches
            times = [run(data, kwargs) for _ in range(rounds)]
            result.setdefault(name, {})["stubbed" if stubbed else "as_shipped"] = statistics.median(times)
    print(json.dumps({"rows": int(len(data["rewards"])), "seconds": result}))


if __name__ == "__main__":
    main()
