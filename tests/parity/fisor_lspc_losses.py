"""FISOR's and LSPC's weights, targets and losses computed again in NumPy (float64) from the formulas of their code
(FISOR: `jaxrl5/agents/fisor/fisor.py`; LSPC: `lspc_iql.py`), on the networks, batch and draws that
tests/e2e/losses.rs wrote with dsrl-train's own results, and compared with them. Prints what it compared; exits 1 on
the first disagreement.

Usage: .venv-sim/bin/python tests/parity/fisor_lspc_losses.py LOSSES.safetensors --fisor JSON --max-latent M \
           --vae-beta B
"""
import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from evaluate_in_python import mlp, noise_net, read_safetensors  # noqa: E402

GAMMA = 0.99


def close(name, ours, theirs, rtol=1e-4, atol=1e-5):
    ours, theirs = np.asarray(ours, np.float64), np.asarray(theirs, np.float64)
    worst = float(np.max(np.abs(ours - theirs) / (atol + rtol * np.abs(theirs))))
    print(f"{name}: largest difference {float(np.max(np.abs(ours - theirs))):.3g} ({worst:.2f} of the tolerance)")
    if worst > 1:
        sys.exit(f"{name} differs: dsrl-train {ours} against NumPy {theirs}")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("file")
    p.add_argument("--fisor", required=True)
    p.add_argument("--max-latent", type=float, required=True)
    p.add_argument("--vae-beta", type=float, required=True)
    args = p.parse_args()
    fisor = json.loads(args.fisor)
    raw = read_safetensors(args.file)
    w = {k[4:]: v.astype(np.float64) for k, v in raw.items() if k.startswith("net/")}
    x = {k[3:]: v.astype(np.float64) for k, v in raw.items() if k.startswith("in/")}
    out = {k[4:]: v.astype(np.float64) for k, v in raw.items() if k.startswith("out/")}
    obs, act = x["obs"], x["act"]
    sa = np.concatenate([obs, act], 1)
    relu = "relu"

    # FISOR: the feasibility-gated weights (fisor.py update_actor).
    q = np.min([mlp(w, f"reward_q.{j}", sa, relu)[:, 0] for j in (0, 1)], 0)
    qc = np.max([mlp(w, f"cost_q.{j}", sa, relu)[:, 0] for j in (0, 1)], 0)
    v = mlp(w, "reward_v", obs, relu)[:, 0]
    vc = mlp(w, "cost_v", obs, relu)[:, 0]
    unsafe = (vc > 0).astype(np.float64)
    safe = ((vc <= 0) & (qc <= 0)).astype(np.float64)
    weights = unsafe * np.clip(np.exp(5.0 * (vc - qc)), 0, 150) + safe * np.clip(np.exp(3.0 * (q - v)), 0, 100)
    print(f"infeasible rows: {int(unsafe.sum())} of {len(obs)}, feasible and safe: {int(safe.sum())}")
    close("FISOR actor weights", out["fisor_weights"], weights)

    # The noise regression on the VP schedule (diffusion.py vp_beta_schedule, fisor.py's noisy actions).
    t_max = fisor["steps"]
    t = np.arange(1, t_max + 1)
    alphas = np.exp(-0.1 / t_max - 0.5 * (10.0 - 0.1) * (2 * t - 1) / t_max**2)
    hats = np.cumprod(alphas)
    steps = x["steps"].astype(int)
    noisy = np.sqrt(hats[steps])[:, None] * act + np.sqrt(1 - hats[steps])[:, None] * x["eps"]
    arch = {"cond_sizes": [None] * fisor["cond"], "num_blocks": fisor["blocks"], "layer_norm": True}
    predicted = noise_net(w, arch, obs, noisy, steps)
    loss = np.mean(weights * np.sum((predicted - x["eps"]) ** 2, -1))
    close("FISOR actor loss", out["fisor_actor_loss"][0], loss)

    # The reachability target (update_qc, critic_type hj) on the recoded cost.
    c = np.where(x["cost"] > 0, 25.0, -1.0)
    mask = 1.0 - x["done"]
    target = mask * ((1 - GAMMA) * c + GAMMA * np.maximum(c, x["next_vc"])) + (1 - mask) * c
    close("FISOR recoded cost", out["fisor_cost"], c)
    close("FISOR reachability target", out["fisor_target"], target)

    # LSPC: the cost-weighted CVAE (VAE_policy's loss) and the safety encoder's regression.
    eps, lw = x["latents"], x["lspc_weights"]
    h = mlp(w, "vae.encoder", sa, relu, activate_last=True)
    mean = mlp(w, "vae.mean", h, relu)
    std = np.exp(np.clip(mlp(w, "vae.log_std", h, relu), -4, 15))
    z = mean + std * eps
    decoded = np.tanh(mlp(w, "vae.decoder", np.concatenate([obs, z], 1), relu))
    kl = -0.5 * args.vae_beta * np.mean(1 + np.log(std**2) - mean**2 - std**2, -1)
    vae = np.mean(lw * (np.sum((decoded - act) ** 2, -1) + kl))
    close("LSPC CVAE loss", out["lspc_vae_loss"][0], vae)
    h = mlp(w, "safety.trunk", obs, relu, activate_last=True)
    log_std = np.clip(mlp(w, "safety.log_std", h, relu), -10, 2)
    latent = np.tanh(mlp(w, "safety.mu", h, relu) + np.exp(log_std) * eps) * args.max_latent
    decoded = np.tanh(mlp(w, "vae.decoder", np.concatenate([obs, latent], 1), relu))
    safety = np.mean(lw * np.sum((decoded - act) ** 2, -1))
    close("LSPC safety encoder loss", out["lspc_safety_loss"][0], safety)


if __name__ == "__main__":
    main()
