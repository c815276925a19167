"""Checks that every task of the catalog builds, resets and steps in the pinned environment, with the catalog's
observation and action dimensions and a finite cost. Run by sim/setup.sh; exits non-zero naming the failures.
usage: check_tasks.py TASKS_CSV
"""
import csv
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from dsrl_sim import tasks  # noqa: E402
from dsrl_sim.batch import Batch  # noqa: E402


def main():
    tasks.quiet()
    failures = []
    rows = list(csv.DictReader(open(sys.argv[1])))
    for row in rows:
        sim_id = row["simulator_env_id"]
        started = time.perf_counter()
        try:
            batch = Batch(sim_id, seeds=[0], auto_reset=False)
            obs = np.frombuffer(batch.reset([0], [0]), dtype=np.float32)
            rng = np.random.default_rng(0)
            for _ in range(5):
                action = rng.uniform(batch.low, batch.high).astype(np.float32)
                out = batch.step([0], action.tobytes())
                cost = np.frombuffer(out[2], dtype=np.float64)[0]
                if not np.isfinite(cost):
                    raise ValueError(f"cost {cost}")
            batch.close()
            want = (int(row["obs_dim_pinned_simulator"]), int(row["act_dim"]))
            if (batch.obs_dim, batch.act_dim) != want or obs.size != want[0]:
                raise ValueError(f"dims {(batch.obs_dim, batch.act_dim)}, catalog says {want}")
            print(f"ok   {sim_id:40s} obs {batch.obs_dim:3d} act {batch.act_dim} "
                  f"({time.perf_counter() - started:.1f} s)", file=sys.stderr)
        except Exception as e:  # report every failing task, not just the first
            failures.append(f"{sim_id}: {type(e).__name__}: {e}")
            print(f"FAIL {sim_id}: {e}", file=sys.stderr)
    if failures:
        sys.exit(f"{len(failures)} of {len(rows)} tasks failed:\n" + "\n".join(failures))
    print(f"all {len(rows)} tasks build, reset and step", file=sys.stderr)


if __name__ == "__main__":
    main()
