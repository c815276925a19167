"""One LSPC training step in LSPC's own PyTorch code, timed: the reference beside `dsrl-train lspc` in
bench/multipass.sh. LSPC is not a package: LSPC_REPO names a clone of PrajwalKoirala/LSPC-Safe-Offline-RL, whose
`lspc_iql.py` is imported as it stands (it needs torch, numpy, tqdm and fsrl, which .venv-bench has).

Batches are drawn from the dataset's transitions (uniform, with replacement) before the clock starts; a few
untimed warm-up steps first. Prints one JSON line: {"ms_per_step": ...}.

Usage: LSPC_REPO=... .venv-bench/bin/python bench/multipass_step_torch.py DATA.parquet --steps 50 --threads 1
"""
import argparse
import json
import os
import sys
import time

import numpy as np
import torch

from offline_step_torch import load, stand_in_loggers


def main():
    p = argparse.ArgumentParser()
    p.add_argument("data")
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--batch-size", type=int, default=1024)
    p.add_argument("--max-latent", type=float, default=0.6)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    sys.path.insert(0, os.environ["LSPC_REPO"])
    stand_in_loggers()  # lspc_iql.py imports fsrl.utils' loggers, which import wandb and TensorBoard
    from lspc_iql import LSPC_IQL_Trainer, LSPC_IQL_kwargs

    d = load(args.data)
    obs, nxt, act, rew, cost = (d[k] for k in ("observations", "next_observations", "actions", "rewards", "costs"))
    done = np.logical_or(d["terminals"], d["timeouts"]).astype(np.float32)
    config = {"max_action": 1.0, "state_dim": obs.shape[1], "action_dim": act.shape[1], "device": "cpu",
              "actor_lr": 3e-4, "qf_lr": 3e-4, "vf_lr": 3e-4, "log_std_min": -10.0, "log_std_max": 2.0,
              "latent_dim": 32, "vae_beta": 0.5, "vae_clamper": args.max_latent, "max_latent_action": args.max_latent}
    torch.manual_seed(0)
    trainer = LSPC_IQL_Trainer(**LSPC_IQL_kwargs(config), iql_tau=0.7, beta_cost=2.0, beta_reward=2.0,
                               exp_adv_max_cost=200.0, exp_adv_max_reward=200.0, safe_qc_vc_threshold=999.0)
    rng = np.random.default_rng(0)
    batches = []
    for _ in range(args.warmup + args.steps):
        i = rng.integers(0, len(obs), args.batch_size)
        batches.append([torch.from_numpy(x[i]) for x in (obs, nxt, act)]
                       + [torch.from_numpy(x[i]).unsqueeze(-1) for x in (rew, cost, done)])
    for b in batches[:args.warmup]:
        trainer.train_one_step(*b)
    start = time.perf_counter()
    for b in batches[args.warmup:]:
        trainer.train_one_step(*b)
    print(json.dumps({"ms_per_step": 1000 * (time.perf_counter() - start) / args.steps}))


if __name__ == "__main__":
    main()
