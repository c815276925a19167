"""Parity reference for the evaluator: plays a dsrl policy checkpoint in-process in Python, with no Rust and no RPC.

The weights are read from policy.safetensors with NumPy (the format is an 8-byte little-endian header length, a JSON
header, raw little-endian tensors), the network is evaluated in float32 NumPy as policy.json declares it, and the
episodes are stepped on the simulator objects the workers host (dsrl_sim.tasks.Env, which carries the seeding fixes
the workers apply). Prints one JSON object with every episode's returns, like `dsrl-admin evaluate --json`.

Usage: .venv-sim/bin/python tests/parity/evaluate_in_python.py POLICY_DIR --sim-id SafetyBallRun-v0 \
           [--episodes 20] [--seed 1000000]
"""
import argparse
import json
import struct
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "sim" / "python"))
from dsrl_sim import tasks  # noqa: E402

DTYPES = {"F32": np.float32, "F64": np.float64}


def read_safetensors(path):
    raw = Path(path).read_bytes()
    (n,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8 : 8 + n])
    data = raw[8 + n :]
    out = {}
    for name, info in header.items():
        if name == "__metadata__":
            continue
        start, end = info["data_offsets"]
        out[name] = np.frombuffer(data[start:end], dtype=DTYPES[info["dtype"]]).reshape(info["shape"])
    return out


def mlp(weights, prefix, x, activation, activate_last=False):
    act = np.tanh if activation == "tanh" else (lambda v: np.maximum(v, np.float32(0)))
    i = 0
    while f"{prefix}.{i}.weight" in weights:
        x = x @ weights[f"{prefix}.{i}.weight"].T + weights[f"{prefix}.{i}.bias"]
        i += 1
        if f"{prefix}.{i}.weight" in weights or activate_last:
            x = act(x)
    return x


def policy_fn(policy_dir):
    config = json.loads((Path(policy_dir) / "policy.json").read_text())
    w = read_safetensors(Path(policy_dir) / "policy.safetensors")
    arch = config["architecture"]
    scale = np.float32(arch["max_action"])
    norm = config.get("observation_normalization")

    def act(obs):
        x = obs.astype(np.float32)[None, :]
        if norm:
            x = (x - np.asarray(norm["mean"], np.float32)) / np.asarray(norm["std"], np.float32)
        if arch["name"] == "gaussian_mlp":
            y = np.tanh(mlp(w, "actor.mu", x, arch["activation"])) * scale
        elif arch["name"] == "mlp_actor":
            y = np.tanh(mlp(w, "actor.net", x, arch["activation"])) * scale
        elif arch["name"] == "squashed_gaussian_mlp":
            h = mlp(w, "actor.trunk", x, arch["activation"], activate_last=True)
            y = np.tanh(mlp(w, "actor.mu", h, arch["activation"])) * scale
        else:
            raise SystemExit(f"unknown architecture {arch['name']}")
        return y[0]

    return config, act


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("policy")
    p.add_argument("--sim-id", required=True)
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--seed", type=int, default=1_000_000)
    args = p.parse_args()
    tasks.quiet()
    config, act = policy_fn(args.policy)
    episodes = []
    for i in range(args.episodes):
        seed = args.seed + i
        env = tasks.make_env(args.sim_id)
        obs = env.reset(seed)
        reward = cost = 0.0
        length = 0
        while True:
            obs, r, c, terminated, truncated, _ = env.step(act(obs))
            # The returns sum float32 rewards and costs in float64, as the evaluator and the datasets do.
            reward += float(np.float32(r))
            cost += float(np.float32(c))
            length += 1
            if terminated or truncated:
                break
        env.close()
        episodes.append({"seed": seed, "reward_return": reward, "cost_return": cost, "length": length})
    print(json.dumps({"task": config["task"], "episodes": episodes}))


if __name__ == "__main__":
    main()
