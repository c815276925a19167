"""Does a simulator environment replay an episode after other episodes, the way a fresh one plays it? For each task:
a fresh `dsrl_sim` env plays an episode from SEED with seeded uniform random actions; a second env first plays two
other episodes (other seeds, other lengths), then the same one. The two are compared exactly (observations, rewards,
costs, ends). A task where they differ keeps state across `reset(seed)`, so environments kept between scorings (a
pool across sessions) would change its episodes. One JSON line per task, with the CPU seconds the fresh env took to
create (the first task's include importing its simulator); run with the simulators' Python:

    .venv-sim/bin/python bench/env_reuse.py SafetyBallCircle-v0 SafetyCarRun-v0 ...
    .venv-sim/bin/python bench/env_reuse.py --seed 11 --steps 150 TASK...
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "sim" / "python"))
from dsrl_sim import tasks  # noqa: E402

tasks.quiet()


def play(env, seed, steps):
    """One episode from `seed` (at most `steps` steps), actions drawn from a generator seeded by `seed`."""
    actions = np.random.default_rng(seed + 7)
    rows = [env.reset(seed)]
    for _ in range(steps):
        obs, reward, cost, terminated, truncated, _ = env.step(actions.uniform(-1, 1, env.act_dim))
        rows.append(np.concatenate([obs, [reward, cost, terminated, truncated]]))
        if terminated or truncated:
            break
    return np.concatenate(rows)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("tasks", nargs="+", help="simulator ids (SafetyBallCircle-v0, SafetyPointGoal1-v0, ...)")
    parser.add_argument("--seed", type=int, default=11, help="the compared episode's seed")
    parser.add_argument("--steps", type=int, default=150, help="steps of the compared episode, at most")
    args = parser.parse_args()
    for task in args.tasks:
        start = time.process_time()
        fresh = tasks.make_env(task)
        made = time.process_time() - start
        first = play(fresh, args.seed, args.steps)
        fresh.close()
        used = tasks.make_env(task)
        play(used, args.seed + 1000, 4 * args.steps)
        play(used, args.seed + 2000, args.steps // 3)
        again = play(used, args.seed, args.steps)
        used.close()
        same = first.shape == again.shape and bool(np.array_equal(first, again))
        print(json.dumps({"task": task, "replays_after_reuse": same, "create_cpu_seconds": round(made, 4)}))


if __name__ == "__main__":
    main()
