"""Golden outputs for the filter tests, made by DSRL's own code.

The reference is `OfflineEnv.pre_process_data` from the PyPI package dsrl==0.1.0. PyPI 0.1.0 differs from the
current reference (GitHub HEAD) only in two bounds (spec §3.9): the density filter is bounded by the catalog's
min/max episode cost and reward (clipped to the data by grid_filter) instead of the data extremes, and the inpaint
cost band uses the catalog's min/max episode cost. This script applies exactly those two changes to the installed
function's source (each patch must match exactly once) and runs it, so the fixtures follow the current behaviour.
The function's matplotlib side effect (a PNG in the working directory) is replaced by a no-op module.

For every case the fixture records the sha256 of each output array's bytes (float32 arrays, bool flags), the row
and episode counts and the first output episodes' returns, or the exception the reference raised.
"""
import argparse
import contextlib
import csv
import hashlib
import inspect
import io
import json
import random
import re
import subprocess
import sys
import textwrap
import types
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

# No plotting, no PNG files: pre_process_data imports matplotlib.pyplot inside the function.
_stub = types.ModuleType("matplotlib.pyplot")
for _name in ["figure", "scatter", "axvline", "legend", "xlabel", "ylabel", "tight_layout", "savefig"]:
    setattr(_stub, _name, lambda *a, **k: None)
sys.modules["matplotlib"] = types.ModuleType("matplotlib")
sys.modules["matplotlib"].pyplot = _stub
sys.modules["matplotlib.pyplot"] = _stub

import dsrl.offline_env as reference  # noqa: E402

KEYS = ["observations", "next_observations", "actions", "rewards", "costs", "terminals", "timeouts"]

# (pattern in 0.1.0's source, replacement with the current reference's bound); whitespace-insensitive.
PATCHES = [
    (r"cost_min=cmin,\s*cost_max=cmax,\s*rew_min=rmin,\s*rew_max=rmax,",
     "cost_min=self.min_episode_cost, cost_max=self.max_episode_cost, "
     "rew_min=self.min_episode_reward, rew_max=self.max_episode_reward,"),
    (r"\(cmax - cmin\) \* pcmin \+ cmin <= cost_returns\[traj_idx\],\s*"
     r"cost_returns\[traj_idx\] <= \(cmax - cmin\) \* pcmax \+ cmin",
     "(self.max_episode_cost - self.min_episode_cost) * pcmin + self.min_episode_cost <= cost_returns[traj_idx], "
     "cost_returns[traj_idx] <= (self.max_episode_cost - self.min_episode_cost) * pcmax + self.min_episode_cost"),
]


def current_pre_process_data():
    source = textwrap.dedent(inspect.getsource(reference.OfflineEnv.pre_process_data))
    for pattern, replacement in PATCHES:
        source, count = re.subn(pattern, replacement, source)
        assert count == 1, f"patch target found {count} times: {pattern}"
    namespace = dict(vars(reference))
    exec(compile(source, "pre_process_data (current bounds)", "exec"), namespace)
    return namespace["pre_process_data"]


PRE_PROCESS_DATA = current_pre_process_data()

DATASETS = {
    "ball": ("OfflineBallRun-v0", 600, 11),
    "car": ("OfflineCarCircle-v0", 400, 12),
    "ant": ("OfflineAntRun-v0", 250, 13),
    "goal": ("OfflinePointGoal1Gymnasium-v0", 40, 14),
    "drive": ("OfflineMetadrive-easydense-v0", 20, 15),
}

# (dataset, our filter string, reference keyword arguments, target_cost or None, python seed)
BIG_SEED = 12345678901234567890


def grid(task, density):
    for row in csv.DictReader(open(Path(__file__).parents[2] / "data" / "density_presets.csv")):
        if row["offline_env_id"] == task and float(row["density"]) == density:
            return {k: int(row[k]) for k in ["cbins", "rbins", "max_npb", "min_npb"]}
    raise KeyError((task, density))


def cases():
    out = []

    def add(ds, text, kwargs, target=None, seed=0):
        out.append({"dataset": ds, "filter": text, "kwargs": kwargs, "target_cost": target, "seed": seed})

    for ds, density in [("ball", 0.5), ("ball", 0.75), ("car", 0.5), ("ant", 0.5), ("goal", 0.25), ("drive", 0.75)]:
        task = DATASETS[ds][0]
        for seed in [0, 1, BIG_SEED]:
            add(ds, f"density={density},seed={seed}", dict(density=density, **grid(task, density)), seed=seed)
    add("ball", "cbins=7,rbins=9,max_npb=3,min_npb=1,seed=5",
        dict(density=0.5, cbins=7, rbins=9, max_npb=3, min_npb=1), seed=5)
    add("car", "cbins=3,rbins=4,max_npb=40,min_npb=0,seed=2",
        dict(density=0.5, cbins=3, rbins=4, max_npb=40, min_npb=0), seed=2)
    for ds in ["ball", "car", "ant"]:
        for p in [0.01, 0.05, 0.1]:
            add(ds, f"noise={p}", dict(outliers_percent=p), target=10)
    add("car", "outliers_percent=0.05,target_cost=40", dict(outliers_percent=0.05), target=40)
    add("goal", "noise=0.05", dict(outliers_percent=0.05), target=20)
    add("ball", "obs_noise=0.05", dict(noise_scale=0.05))
    add("ant", "noise_scale=0.1", dict(noise_scale=0.1))
    add("goal", "obs_noise=0.2", dict(noise_scale=0.2))
    add("drive", "obs_noise=0.1", dict(noise_scale=0.1))
    for ds in ["ball", "car", "ant"]:
        add(ds, "discard=tempting", dict(inpaint_ranges=((0.5, 1.0, 0.5, 1.0),)))
        add(ds, "discard=low-reward", dict(inpaint_ranges=((0.0, 0.5, 0.0, 0.5),)))
    add("car", "inpaint=0.3:0.6:0.2:0.8", dict(inpaint_ranges=((0.3, 0.6, 0.2, 0.8),)))
    add("ball", "inpaint=0.1:0.9:0:0.35", dict(inpaint_ranges=((0.1, 0.9, 0.0, 0.35),)))
    add("car", "epsilon=50", dict(epsilon=50.0), target=10)
    add("car", "epsilon=-30", dict(epsilon=-30.0), target=10)
    add("ant", "epsilon=100,target_cost=40", dict(epsilon=100.0), target=40)
    add("ball", "epsilon=-200,target_cost=20", dict(epsilon=-200.0), target=20)
    # Combinations, in DSRL's pipeline order.
    add("car", "density=0.75,seed=3,noise=0.05,obs_noise=0.1",
        dict(density=0.75, **grid("OfflineCarCircle-v0", 0.75), outliers_percent=0.05, noise_scale=0.1),
        target=10, seed=3)
    add("ball", "noise=0.1,discard=tempting", dict(outliers_percent=0.1, inpaint_ranges=((0.5, 1.0, 0.5, 1.0),)),
        target=10)
    add("car", "noise=0.05,inpaint=0:1:0.8:1", dict(outliers_percent=0.05, inpaint_ranges=((0.0, 1.0, 0.8, 1.0),)),
        target=10)
    add("ant", "noise=0.05,epsilon=80,target_cost=20", dict(outliers_percent=0.05, epsilon=80.0), target=20)
    add("ball", "density=0.5,seed=9,epsilon=-100", dict(density=0.5, **grid("OfflineBallRun-v0", 0.5), epsilon=-100.0),
        target=10, seed=9)
    add("car", "density=0.5,seed=4,discard=low-reward,obs_noise=0.05",
        dict(density=0.5, **grid("OfflineCarCircle-v0", 0.5), inpaint_ranges=((0.0, 0.5, 0.0, 0.5),),
             noise_scale=0.05), seed=4)
    add("goal", "density=0.5,seed=1,noise=0.1,obs_noise=0.01",
        dict(density=0.5, **grid("OfflinePointGoal1Gymnasium-v0", 0.5), outliers_percent=0.1, noise_scale=0.01),
        target=20, seed=1)
    # Cases where the reference fails: we must refuse them too.
    add("ball", "noise=0.9", dict(outliers_percent=0.9), target=10)
    add("car", "epsilon=-5,target_cost=1000", dict(epsilon=-5.0), target=1000)
    add("ball", "inpaint=0.99:1:0:1", dict(inpaint_ranges=((0.99, 1.0, 0.0, 1.0),)))
    return out


def load(path, task_obs, task_act):
    table = pq.read_table(path)
    data = {}
    for key, dim in [("observations", task_obs), ("next_observations", task_obs), ("actions", task_act)]:
        data[key] = table.column(key).combine_chunks().flatten().to_numpy().astype(np.float32).reshape(-1, dim)
    for key in ["rewards", "costs"]:
        data[key] = table.column(key).to_numpy().astype(np.float32)
    for key in ["terminals", "timeouts"]:
        data[key] = table.column(key).to_numpy(zero_copy_only=False).astype(bool)
    return data


def digest(array):
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()


def main():
    args = argparse.ArgumentParser()
    args.add_argument("--make-dataset", required=True)
    args.add_argument("--work", required=True)
    args.add_argument("--out", required=True)
    a = args.parse_args()
    catalog = {row["offline_env_id"]: row for row in csv.DictReader(open(Path(__file__).parents[2] / "data" / "tasks.csv"))}
    datasets = {}
    for name, (task, episodes, seed) in DATASETS.items():
        path = Path(a.work) / f"{name}.parquet"
        subprocess.run([a.make_dataset, "--task", task, "--episodes", str(episodes), "--seed", str(seed), str(path)],
                       check=True, stdout=subprocess.DEVNULL)
        row = catalog[task]
        datasets[name] = (task, load(path, int(row["obs_dim_pinned_simulator"]), int(row["act_dim"])), row)
    results = []
    for case in cases():
        task, data, row = datasets[case["dataset"]]
        env = reference.OfflineEnv(
            max_episode_reward=float(row["max_episode_reward"]), min_episode_reward=float(row["min_episode_reward"]),
            max_episode_cost=float(row["max_episode_cost"]), min_episode_cost=float(row["min_episode_cost"]))
        target = case["target_cost"]
        if target is None:
            target = float(row["cost_thresholds"].split(";")[0])
        env.set_target_cost(target)
        kwargs = dict(case["kwargs"])
        random.seed(case["seed"])
        expected = {}
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                out = PRE_PROCESS_DATA(env, {k: v.copy() for k, v in data.items()}, **kwargs)
            dones = np.nonzero(out["terminals"] | out["timeouts"])[0]
            starts = np.concatenate([[0], dones[:-1] + 1])
            returns = [[float(np.sum(out["costs"][s:e + 1])), float(np.sum(out["rewards"][s:e + 1]))]
                       for s, e in zip(starts, dones)]
            expected = {
                "rows": int(len(out["rewards"])),
                "episodes": int(len(dones)),
                "sha256": {k: digest(out[k]) for k in KEYS},
                # For reading a mismatch: the first output episodes' (cost, reward) returns.
                "returns_head": returns[:10],
            }
        except Exception as e:  # the reference fails on this input
            expected = {"error": f"{type(e).__name__}: {e}"}
        results.append({**case, "expected": expected})
        print(case["dataset"], case["filter"], expected.get("rows", expected.get("error")), file=sys.stderr)
    doc = {
        "generated_by": "tests/golden/make_golden.sh",
        "reference": "dsrl==0.1.0 pre_process_data with the current reference's bounds, numpy " + np.__version__
                     + ", python " + sys.version.split()[0],
        "datasets": {k: {"task": t, "episodes": e, "seed": s} for k, (t, e, s) in DATASETS.items()},
        "cases": results,
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
