"""`gym.make` of the package steps the real simulator: the same adapter the server's workers host, with the same
seed, gives the same episode. Run by tests/e2e/python_package.rs in .venv-sim with the wheel and sim/python on the
path; prints one JSON line."""
import json

import gymnasium as gym
import numpy as np

import dsrl_client
from dsrl_sim.tasks import make_env

TASK, SIM, SEED, STEPS = "OfflineBallRun-v0", "SafetyBallRun-v0", 7, 25

env = gym.make(TASK)
assert isinstance(env, dsrl_client.OfflineEnv)
rng = np.random.default_rng(0)
actions = rng.uniform(-1, 1, (STEPS, env.action_space.shape[0]))
obs, _ = env.reset(seed=SEED)
ours = [obs]
for a in actions:
    obs, reward, terminated, truncated, info = env.step(a)
    ours.append(np.concatenate([obs, [reward, info["cost"]]]))
env.close()

worker = make_env(SIM)
theirs = [worker.reset(SEED)]
for a in actions:
    obs, reward, cost, _, _, _ = worker.step(a)
    theirs.append(np.concatenate([obs, [reward, cost]]))
worker.close()

# The horizon is the env's own (no TimeLimit wrapper): a short horizon shows where it truncates.
short = gym.make(TASK, max_episode_steps=5)
short.reset(seed=SEED)
truncated_at = next(i + 1 for i in range(10) if short.step(actions[i])[3])
short.close()

print(json.dumps({"steps": len(actions), "same_as_worker_adapter": all(np.array_equal(a, b) for a, b in
                                                                            zip(ours, theirs)),
                  "horizon": 5, "truncated_at": truncated_at}))
