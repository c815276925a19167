"""Checks README.md's PyTorch export snippet against OSRL's own modules.

Builds OSRL's MLPActor, BCQ-L actor + VAE, and CDT (osrl-lib from PyPI, seeded), runs the README's ```python block
verbatim on them to write three checkpoints, then plays each checkpoint through tests/parity/evaluate_in_python.py
(the NumPy reference that the end-to-end tests hold to the Rust evaluator) and through OSRL's own forward pass and,
for the CDT, OSRL's rollout logic (CDTTrainer.rollout with the environment replaced by a seeded synthetic sequence).
Exits non-zero when an action differs by more than 1e-5. Prints one JSON line with the largest differences.

OSRL's package imports its training code too (fsrl, gymnasium, tqdm, scipy, yaml); the modules need none of it, so those
imports are stubbed.
Usage: .venv-bench/bin/python tests/parity/osrl_export_check.py   (see osrl_export_check.sh)
"""
import json
import os
import re
import sys
import tempfile
import types
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
STUBS = ["gymnasium", "fsrl", "fsrl.utils", "tqdm", "tqdm.auto", "scipy", "scipy.optimize", "yaml", "dsrl_sim",
         "dsrl_sim.tasks"]
for name in STUBS:
    sys.modules.setdefault(name, types.ModuleType(name))
sys.modules["fsrl.utils"].DummyLogger = sys.modules["fsrl.utils"].WandbLogger = object
sys.modules["scipy.optimize"].minimize = None
sys.modules["tqdm.auto"].trange = range
sys.modules["gymnasium"].Env = object
sys.modules["dsrl_sim"].tasks = sys.modules["dsrl_sim.tasks"]
sys.path.insert(0, str(ROOT / "tests" / "parity"))

import evaluate_in_python as reference  # noqa: E402
from osrl.algorithms.cdt import CDT  # noqa: E402
from osrl.common.net import VAE, MLPActor, MLPGaussianPerturbationActor  # noqa: E402

OBS, ACT, STEPS, THRESHOLD = 7, 2, 40, 20.0


def readme_snippet():
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    return next(b for b in blocks if "def write(folder" in b)


def main():
    torch.manual_seed(0)
    actor = MLPActor(OBS, ACT, [256, 256], torch.nn.ReLU, 1.0)
    model = types.SimpleNamespace(
        actor=MLPGaussianPerturbationActor(OBS, ACT, [256, 256], torch.nn.Tanh, 0.05, 1.0),
        vae=VAE(OBS, ACT, 400, 2 * ACT, 1.0),
    )
    cdt = CDT(OBS, ACT, 1.0, seq_len=10, episode_len=200, embedding_dim=128, num_layers=3, num_heads=8,
              attention_dropout=0.1, residual_dropout=0.1, embedding_dropout=0.1, use_rew=True, use_cost=True,
              cost_transform=True, stochastic=True, action_head_layers=1)
    cdt.eval()
    rng = np.random.default_rng(1)
    obs = rng.standard_normal((STEPS, OBS)).astype(np.float32)
    rewards = rng.uniform(0, 5, STEPS)
    costs = (rng.uniform(0, 1, STEPS) > 0.7).astype(float)
    worst = {}
    with tempfile.TemporaryDirectory() as out, torch.no_grad():
        os.chdir(out)
        exec(readme_snippet(), {"actor": actor, "model": model, "cdt": cdt})

        act, _ = reference.policy_fn("bc-safe-20", THRESHOLD)[1](0)
        worst["mlp_actor"] = max(float(np.abs(actor(torch.from_numpy(o)[None])[0].numpy() - act(o)).max()) for o in obs)

        seed = 7
        act, _ = reference.policy_fn("bcql-20", THRESHOLD)[1](seed)
        latents = reference.SplitMix64(seed)
        diffs = []
        for o in obs:
            z = torch.tensor([[min(max(latents.normal(), -0.5), 0.5) for _ in range(2 * ACT)]], dtype=torch.float32)
            x = torch.from_numpy(o)[None]
            diffs.append(float(np.abs(model.actor(x, model.vae.decode(x, z))[0].numpy() - act(o)).max()))
        worst["bcq_actor"] = max(diffs)

        # OSRL's CDTTrainer.rollout: target (575, 20) scaled by reward_scale 0.1; rewards arrive scaled by its wrapper.
        act, observe = reference.policy_fn("cdt", THRESHOLD)[1](0)
        L, K = 200, 10
        states, actions = torch.zeros(1, L + 1, OBS), torch.zeros(1, L, ACT)
        returns, ctg = torch.zeros(1, L + 1), torch.zeros(1, L + 1)
        time_steps = torch.arange(L).view(1, -1)
        states[:, 0] = torch.from_numpy(obs[0])
        returns[:, 0] = 575 * 0.1
        ctg[:, 0] = THRESHOLD
        diffs = []
        for step in range(STEPS - 1):
            window = slice(max(0, step + 1 - K), step + 1)
            means, _, _ = cdt(states[:, window], actions[:, window], returns[:, window], ctg[:, window],
                              time_steps[:, window], None, None)
            theirs = means.mean.clamp(-1.0, 1.0)[0, -1]
            diffs.append(float(np.abs(theirs.numpy() - act(obs[step])).max()))
            actions[:, step] = theirs
            states[:, step + 1] = torch.from_numpy(obs[step + 1])
            returns[:, step + 1] = returns[:, step] - rewards[step] * 0.1
            ctg[:, step + 1] = ctg[:, step] - costs[step]
            observe(rewards[step], costs[step])
        worst["cdt"] = max(diffs)
    print(json.dumps({"largest_action_difference": worst, "torch": torch.__version__}))
    if max(worst.values()) > 1e-5:
        sys.exit(1)


if __name__ == "__main__":
    main()
