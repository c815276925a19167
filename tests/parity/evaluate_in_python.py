"""Parity reference for the evaluator: plays a dsrl policy checkpoint in-process in Python, with no Rust and no RPC.

The weights are read from policy.safetensors with NumPy (the format is an 8-byte little-endian header length, a JSON
header, raw little-endian tensors), the network is evaluated in float32 NumPy as policy.json declares it, and the
episodes are stepped on the simulator objects the workers host (dsrl_sim.tasks.Env, which carries the seeding fixes
the workers apply). Prints one JSON object with every episode's returns, like `dsrl-admin evaluate --json`.

Every architecture of the format is written out here independently of the Rust code: the MLP actors, the BCQ
actor (VAE decoder + perturbation; its latents drawn from SplitMix64 + Box-Muller seeded with the episode seed, as
the evaluator does) and the CDT (OSRL's rollout: one episode, the last seq_len timesteps unpadded, reward- and
cost-to-go kept in float32), CAPS's switch, the diffusion sampler (DDPM over the candidates, every draw from the
episode's SplitMix64 in the evaluator's order) and the latent policy. Conditioned policies play at --cost-threshold.

Each episode is played on a new env by default, so that an episode depends on its seed alone. `bench/score.sh` plays
it as OSRL's evaluation does instead: `--one-env` (one env, reset with each episode's seed) and, for the loop a
researcher runs on the simulators as published, `--library-code` (dsrl_sim's speed-ups left out,
sim/python/dsrl_sim/speedups.py).

Usage: .venv-sim/bin/python tests/parity/evaluate_in_python.py POLICY_DIR --sim-id SafetyBallRun-v0 \
           [--episodes 20] [--seed 1000000] [--cost-threshold 10] [--one-env] [--library-code]
"""
import argparse
import json
import math
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


class SplitMix64:
    """The evaluator's per-episode generator (dsrl-policy noise.rs): SplitMix64, uniforms in (0, 1), Box-Muller."""

    MASK = (1 << 64) - 1

    def __init__(self, seed):
        self.state = seed & self.MASK

    def next_u64(self):
        self.state = (self.state + 0x9E3779B97F4A7C15) & self.MASK
        z = self.state
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & self.MASK
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & self.MASK
        return z ^ (z >> 31)

    def uniform(self):
        return ((self.next_u64() >> 11) + 0.5) / float(1 << 53)

    def normal(self):
        u1, u2 = self.uniform(), self.uniform()
        return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)


def linear(w, name, x):
    return x @ w[f"{name}.weight"].T + w[f"{name}.bias"]


def layer_norm(w, name, x):
    mean = x.mean(-1, keepdims=True)
    var = ((x - mean) ** 2).mean(-1, keepdims=True)
    return (x - mean) / np.sqrt(var + np.float32(1e-5)) * w[f"{name}.weight"] + w[f"{name}.bias"]


_erf = np.vectorize(math.erf, otypes=[np.float64])


def gelu(x):
    return (0.5 * x * (1.0 + _erf(x.astype(np.float64) / math.sqrt(2.0)))).astype(np.float32)


def softmax(x):
    e = np.exp(x - x.max(-1, keepdims=True))
    return e / e.sum(-1, keepdims=True)


def cdt_action(w, arch, states, actions, rtg, ctg, steps):
    """OSRL CDT.forward for one unpadded sequence of T timesteps; the action head's mean at the last one."""
    t = len(steps)
    d, heads = arch["embedding_dim"], arch["num_heads"]
    time = w["cdt.timestep_emb.weight"][steps]
    if arch["cost_transform"]:
        ctg = np.float32(50.0) - ctg
    tokens = [
        linear(w, "cdt.return_emb", rtg[:, None]) + time,
        linear(w, "cdt.cost_emb", ctg[:, None]) + time,
        linear(w, "cdt.state_emb", states) + time,
        linear(w, "cdt.action_emb", actions) + time,
    ]
    x = np.stack(tokens, axis=1).reshape(4 * t, d)
    x = layer_norm(w, "cdt.emb_norm", x)
    hd = d // heads
    causal = np.triu(np.full((4 * t, 4 * t), -np.inf, np.float32), 1)
    for i in range(arch["num_layers"]):
        p = f"cdt.blocks.{i}"
        h = layer_norm(w, f"{p}.norm1", x)
        qkv = h @ w[f"{p}.attention.in_proj_weight"].T + w[f"{p}.attention.in_proj_bias"]
        q, k, v = (qkv[:, j * d : (j + 1) * d].reshape(4 * t, heads, hd).transpose(1, 0, 2) for j in range(3))
        att = softmax((q / np.float32(math.sqrt(hd))) @ k.transpose(0, 2, 1) + causal) @ v
        x = x + linear(w, f"{p}.attention.out_proj", att.transpose(1, 0, 2).reshape(4 * t, d))
        x = x + linear(w, f"{p}.mlp.2", gelu(linear(w, f"{p}.mlp.0", layer_norm(w, f"{p}.norm2", x))))
    x = layer_norm(w, "cdt.out_norm", x)
    state_out = x.reshape(t, 4, d)[:, 2]
    return linear(w, "cdt.action_head.mu", state_out)[-1]


def mish(v):
    # softplus as the evaluator writes it: max(v, 0) + log(1 + exp(-|v|)).
    softplus = np.maximum(v, 0) + np.log(1 + np.exp(-np.abs(v)))
    return v * np.tanh(softplus)


def noise_net(w, arch, x, a, t):
    """FISOR's noise prediction (`diffusion` architecture) for rows of observations x, noised actions a and step
    indices t (one per row)."""
    f = (np.asarray(t, np.float32)[:, None] * w["actor.time.kernel"][:, 0][None, :]) * np.float32(2 * math.pi)
    cond = np.concatenate([np.cos(f), np.sin(f)], 1)
    n = len(arch["cond_sizes"])
    for i in range(n):
        cond = linear(w, f"actor.cond.{i}", cond)
        if i + 1 < n:
            cond = mish(cond)
    h = linear(w, "actor.input", np.concatenate([a, x, cond], 1))
    for k in range(arch["num_blocks"]):
        y = layer_norm(w, f"actor.blocks.{k}.norm", h) if arch["layer_norm"] else h
        h = h + linear(w, f"actor.blocks.{k}.project", mish(linear(w, f"actor.blocks.{k}.expand", y)))
    return linear(w, "actor.output", mish(h))


def policy_fn(policy_dir, cost_threshold):
    """Returns (config, new_episode(seed) -> (act(obs) -> action, observe(reward, cost)))."""
    config = json.loads((Path(policy_dir) / "policy.json").read_text())
    w = read_safetensors(Path(policy_dir) / "policy.safetensors")
    arch = config["architecture"]
    scale = np.float32(arch["max_action"])
    norm = config.get("observation_normalization")
    conditioning = config.get("conditioning", {"kind": "unconditioned"})

    def prepare(obs):
        x = obs.astype(np.float32)[None, :]
        if norm:
            x = (x - np.asarray(norm["mean"], np.float32)) / np.asarray(norm["std"], np.float32)
        if conditioning["kind"] == "target_cost":
            x = np.concatenate([x, np.full((1, 1), cost_threshold, np.float32)], axis=1)
        return x

    def memoryless(x, _state):
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

    def bcq(x, state):
        z = np.array(
            [[min(max(state["noise"].normal(), -0.5), 0.5) for _ in range(arch["latent_dim"])]], np.float32
        )
        proposal = np.tanh(mlp(w, "vae.decoder", np.concatenate([x, z], 1), "relu")) * scale
        nudge = np.float32(arch["phi"]) * scale * np.tanh(
            mlp(w, "actor.pi", np.concatenate([x, proposal], 1), arch["activation"])
        )
        return np.clip(proposal + nudge, -scale, scale)[0]

    def diffusion(x, state):
        sampler = arch["sampler"]
        steps, n, act_dim = sampler["steps"], sampler["candidates"], config["act_dim"]
        t_max = float(steps)
        alphas = [
            math.exp(-sampler["beta_min"] / t_max - 0.5 * (sampler["beta_max"] - sampler["beta_min"]) * (2 * t - 1) / t_max**2)
            for t in range(1, steps + 1)
        ]
        hats = np.cumprod(alphas)

        def draws():
            return np.array([state["noise"].normal() for _ in range(n * act_dim)], np.float32).reshape(n, act_dim)

        xs = x.repeat(n, 0)
        a = draws()
        for t in reversed(range(steps)):
            eps = noise_net(w, arch, xs, a, np.full(len(xs), t))
            a = (a - eps * np.float32((1 - alphas[t]) / math.sqrt(1 - hats[t]))) * np.float32(1 / math.sqrt(alphas[t]))
            if t > 0:
                a = a + draws() * np.float32(math.sqrt(1 - alphas[t]) * sampler["temperature"])
            if sampler["clip"]:
                a = np.clip(a, -1, 1)
        a = np.clip(a, -1, 1)
        xa = np.concatenate([xs, a], 1)
        members = range(arch["critic_members"])
        if sampler["choice"] == "min_cost_q":
            score = np.max([mlp(w, f"cost_q.{j}", xa, "relu")[:, 0] for j in members], 0)
            best = int(np.argmin(score))
        else:
            score = np.min([mlp(w, f"reward_q.{j}", xa, "relu")[:, 0] for j in members], 0)
            best = int(np.argmax(score))
        return a[best] * scale

    def latent_policy(x, state):
        eps = np.array([[state["noise"].normal() for _ in range(arch["latent_dim"])]], np.float32)
        bound = np.float32(arch["max_latent"])
        if arch["latent"] == "safety_encoder":
            h = mlp(w, "safety.trunk", x, "relu", activate_last=True)
            log_std = np.clip(mlp(w, "safety.log_std", h, "relu"), np.float32(-10), np.float32(2))
            z = np.tanh(mlp(w, "safety.mu", h, "relu") + np.exp(log_std) * eps) * bound
        else:
            z = np.clip(eps, -bound, bound)
        return (np.tanh(mlp(w, "vae.decoder", np.concatenate([x, z], 1), "relu")) * scale)[0]

    def cdt(x, state):
        state["states"].append(x[0])
        state["actions"].append(np.zeros(config["act_dim"], np.float32))
        k = arch["seq_len"]
        n = len(state["states"])
        lo = max(0, n - k)
        a = cdt_action(
            w,
            arch,
            np.stack(state["states"][lo:]),
            np.stack(state["actions"][lo:]),
            np.array(state["rtg"][lo:n], np.float32),
            np.array(state["ctg"][lo:n], np.float32),
            np.arange(lo, n),
        )
        a = np.clip(a, -scale, scale).astype(np.float32)
        state["actions"][-1] = a
        return a

    def caps(x, state):
        # Every head's action, the critic pairs' predictions for each, and CAPS's switch on the budget left.
        h = mlp(w, "actor.trunk", x, "relu", activate_last=True)
        actions = [np.tanh(mlp(w, f"actor.head.{k}", h, "relu")) * scale for k in range(arch["num_heads"])]
        predicted = []
        for a in actions:
            xa = np.concatenate([x, a], 1)
            reward = min(mlp(w, f"reward_q.{j}", xa, "relu")[0, 0] for j in (0, 1))
            cost = -min(mlp(w, f"cost_q.{j}", xa, "relu")[0, 0] for j in (0, 1))
            predicted.append((float(reward), float(cost)))
        left = max(arch["episode_len"] - state["steps"], 1)
        gamma = arch["gamma"]
        remaining = float(np.float32(cost_threshold)) * arch["cost_scale"] - state["spent"]
        limit = max(remaining, 0.0) * (1 - gamma**left) / (1 - gamma) / left
        fits = [k for k, (_, c) in enumerate(predicted) if c < limit]
        if fits:
            chosen = max(fits, key=lambda k: (predicted[k][0], -k))
        else:
            chosen = min(range(len(predicted)), key=lambda k: (predicted[k][1], k))
        return actions[chosen][0]

    if arch["name"] == "cdt":
        target = next(t for t in conditioning["targets"] if t["cost_threshold"] == cost_threshold)
        start = (
            np.float32(target["reward_return"] * arch["reward_scale"]),
            np.float32(target["cost_return"] * arch["cost_scale"]),
        )

    def new_episode(seed):
        state = {"noise": SplitMix64(seed), "states": [], "actions": [], "spent": 0.0, "steps": 0}
        if arch["name"] == "cdt":
            state["rtg"], state["ctg"] = [start[0]], [start[1]]
        step = {"bcq_actor": bcq, "cdt": cdt, "caps": caps, "diffusion": diffusion, "latent_policy": latent_policy}.get(
            arch["name"], memoryless
        )

        def act(obs):
            return step(prepare(obs), state)

        def observe(reward, cost):
            if arch["name"] == "caps":
                state["spent"] += cost * arch["cost_scale"]
                state["steps"] += 1
            if arch["name"] == "cdt":
                # In float32, as OSRL's rollout tensors hold them.
                state["rtg"].append(np.float32(state["rtg"][-1] - np.float32(reward * arch["reward_scale"])))
                state["ctg"].append(np.float32(state["ctg"][-1] - np.float32(cost * arch["cost_scale"])))

        return act, observe

    return config, new_episode


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("policy")
    p.add_argument("--sim-id", required=True)
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--seed", type=int, default=1_000_000)
    p.add_argument("--cost-threshold", type=float, default=None)
    p.add_argument("--one-env", action="store_true", help="play every episode on one env, as OSRL's evaluation does")
    p.add_argument("--library-code", action="store_true",
                   help="the simulators' own Python, without dsrl_sim's speed-ups")
    args = p.parse_args()
    tasks.quiet()
    if args.library_code:
        from dsrl_sim import speedups

        speedups.apply_safety_gymnasium = speedups.apply_bullet_safety_gym = lambda: None
    config, new_episode = policy_fn(args.policy, args.cost_threshold)
    episodes = []
    env = tasks.make_env(args.sim_id) if args.one_env else None
    for i in range(args.episodes):
        seed = args.seed + i
        if not args.one_env:
            env = tasks.make_env(args.sim_id)
        obs = env.reset(seed)
        act, observe = new_episode(seed)
        reward = cost = 0.0
        length = 0
        while True:
            obs, r, c, terminated, truncated, _ = env.step(act(obs))
            observe(r, c)
            # The returns sum float32 rewards and costs in float64, as the evaluator and the datasets do.
            reward += float(np.float32(r))
            cost += float(np.float32(c))
            length += 1
            if terminated or truncated:
                break
        if not args.one_env:
            env.close()
        episodes.append({"seed": seed, "reward_return": reward, "cost_return": cost, "length": length})
    print(json.dumps({"task": config["task"], "episodes": episodes}))


if __name__ == "__main__":
    main()
