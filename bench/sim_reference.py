"""In-process Python reference for bench/sim.sh: steps K environments of one task with uniform random actions and
reset-on-done, with no RPC at all, and prints one JSON line like dsrl-sim-bench does.

--mode raw:   the simulator's own env objects (gymnasium / safety_gymnasium / SafeMetaDrive) in a Python loop,
              the way a researcher steps them; MetaDrive allows one env per process, so raw MetaDrive is K=1 only.
--mode batch: dsrl_sim.batch.Batch, the exact code the worker runs, called directly (MetaDrive: one child process
              per env, as in the worker).
--mode sweep: MetaDrive only, the raw loop doing a dataset sweep's work: one SafeMetaDrive env plays settings
              FIRST..LAST-1 of the task's recipe (data/recipes; easysparse: 50 noisy-IDM settings, acceleration
              factor 0.0..5.4 outer, target speed 5..21 km/h inner, as pipeline/src/recipe.rs orders and computes
              them) with the recipe's episode seeds, switching the driver on reset. Timed whole, creating the env
              included, as `dsrl-admin collect` is.
"""
import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "sim" / "python"))
from dsrl_sim import batch as batch_module, tasks  # noqa: E402

tasks.quiet()


def raw(task, k, steps, warmup, seed, controller=None):
    envs = [tasks.make_env(task, controller) for _ in range(k)]
    raw_envs = [e._env for e in envs]
    family = envs[0].family
    low, high = envs[0].low, envs[0].high
    rng = np.random.default_rng(seed)
    for i, env in enumerate(raw_envs):
        env.reset(seed=seed + i)
    resets = [0] * k
    ended = 0
    for n in range(warmup + steps):
        if n == warmup:
            started = time.perf_counter()
        for i, env in enumerate(raw_envs):
            action = rng.uniform(low, high)
            if family == tasks.SAFETY_GYMNASIUM:
                _, _, _, terminated, truncated, _ = env.step(action)
            else:
                _, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                ended += 1
                resets[i] += 1
                env.reset(seed=seed + i + resets[i] * k)
    return time.perf_counter() - started, ended, envs[0]


def batched(task, k, steps, warmup, seed, controller=None):
    b = batch_module.Batch(task, [seed + i for i in range(k)], auto_reset=True, controller=controller)
    indices = list(range(k))
    b.reset(indices, [seed + i for i in indices])
    rng = np.random.default_rng(seed)
    ended = 0
    for n in range(warmup + steps):
        if n == warmup:
            started = time.perf_counter()
        actions = rng.uniform(b.low, b.high, size=(k, b.act_dim)).astype(np.float32).tobytes()
        out = b.step(indices, actions)
        ended += int(np.frombuffer(out[3], np.uint8).sum() + np.frombuffer(out[4], np.uint8).sum())
    seconds = time.perf_counter() - started
    b.close()
    return seconds, ended, None


def sweep_settings(task):
    """The recipe's sweep as `dsrl-admin collect` plays it (pipeline/src/recipe.rs): (acceleration factor, target
    speed) with the factor outer, each factor `start + i * step`, and the recipe's seed."""
    import tomllib

    name = task[len("SafeMetaDrive-"):]
    recipe = Path(__file__).resolve().parent.parent / "data" / "recipes" / f"OfflineMetadrive-{name}.toml"
    with open(recipe, "rb") as f:
        toml = tomllib.load(f)
    acc = toml["idm_sweep"]["acc_factor"]
    n = max(0, math.ceil((acc["stop"] - acc["start"]) / acc["step"]))
    factors = [acc["start"] + i * acc["step"] for i in range(n)]
    speeds = [float(v) for v in toml["idm_sweep"]["target_speeds"]]
    return [(speed, factor) for factor in factors for speed in speeds], int(toml["seed"])


def sweep(task, first, last, episodes_per_setting):
    """-> (seconds, env-steps, episodes): the raw loop playing settings first..last-1, creating its env included."""
    started = time.perf_counter()
    every, recipe_seed = sweep_settings(task)
    settings = every[first:last]
    controller = lambda speed, acc: {"idm": {"target_speed": speed, "acc_factor": acc}}  # noqa: E731
    env = tasks.make_env(task, controller(*settings[0]))._env
    steps = episodes = 0
    for offset, (speed, acc) in enumerate(settings):
        env.set_controller(controller(speed, acc))
        for episode in range(episodes_per_setting):
            # pipeline/src/recipe.rs episode_seed
            env.reset(seed=(recipe_seed * 1_000_003 + (first + offset) * 100_000 + episode) % 2**64)
            while True:
                _, _, terminated, truncated, _ = env.step([0.0, 0.0])
                steps += 1
                if terminated or truncated:
                    break
            episodes += 1
    env.close()
    return time.perf_counter() - started, steps, episodes


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", required=True)
    parser.add_argument("--envs", type=int, default=1)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--mode", choices=["raw", "batch", "sweep"], default="raw")
    parser.add_argument("--settings", metavar="FIRST:LAST", default="0:50", help="sweep: the settings to play")
    parser.add_argument("--episodes-per-setting", type=int, default=1, help="sweep: episodes of each setting")
    parser.add_argument("--idm", metavar="SPEED,ACC", help="MetaDrive: DSRL's noisy IDM driver steers (target speed "
                        "km/h, acceleration factor) as in the dataset sweep; the random actions are then ignored")
    args = parser.parse_args()
    if args.mode == "sweep":
        first, last = (int(v) for v in args.settings.split(":"))
        seconds, env_steps, episodes = sweep(args.task, first, last, args.episodes_per_setting)
        print(json.dumps({"task": args.task, "envs": 1, "mode": "sweep", "settings": args.settings,
                          "env_steps": env_steps, "seconds": round(seconds, 3),
                          "env_steps_per_s": round(env_steps / seconds, 1), "episodes_ended": episodes}))
        return
    run = raw if args.mode == "raw" else batched
    controller = None
    if args.idm:
        speed, acc = (float(v) for v in args.idm.split(","))
        controller = {"idm": {"target_speed": speed, "acc_factor": acc}}
    seconds, ended, _ = run(args.task, args.envs, args.steps, args.warmup, args.seed, controller)
    env_steps = args.steps * args.envs
    print(json.dumps({"task": args.task, "envs": args.envs, "mode": args.mode, "env_steps": env_steps,
                      "seconds": round(seconds, 3), "env_steps_per_s": round(env_steps / seconds, 1),
                      "episodes_ended": ended}))


if __name__ == "__main__":
    main()
