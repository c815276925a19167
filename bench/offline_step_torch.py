"""PyTorch reference for bench/offline_step.sh: one training step of OSRL's own BCQ-L, BEAR-L, CPQ or COptiDICE,
run from the installed `osrl-lib` package (its model classes and Trainers, not a copy) on CPU with the OfflineCarRun-v0
settings of OSRL's configs (spec 5.6-5.8): batch 512, hidden [256, 256], VAE hidden 400, reward scale 0.1, cost scale
1, gamma 0.99, tau 0.005, episode length 200, cost limit 10, and each algorithm's own learning rates and constants
(see ALGOS below).

Batches are drawn uniformly with replacement, as OSRL's TransitionDataset does (whose `done` = terminals | timeouts
and `is_init` flags are used as it builds them), and are all built before the clock starts: the timed loop is
`trainer.train_one_step(...)` alone. The time to gather a batch is measured apart and reported as
`batch_ms_per_step`. After WARMUP untimed steps, N steps are timed. Prints one JSON line.

fsrl.utils (where OSRL's Trainers get DummyLogger) imports wandb and TensorBoard when it loads, for loggers that
this benchmark never builds. When those packages are missing, empty stand-in modules take their place, so
.venv-bench does not need them.

CDT (`--algo cdt`, spec 5.4) runs OSRL's CDT model and CDTTrainer with the base config (embedding 128, 3 layers,
8 heads, context 10, dropouts 0.1, batch 2048, AdamW lr 1e-4 / weight decay 1e-4, clip 0.25, warm-up 500, cost
weight 0.02, stochastic head, temperature 0.1) on windows of 10 steps drawn as dsrl-train draws them (trajectory
∝ max(0, 70 − cost return), uniform start, zero padding at the end); OSRL's augmentation is not part of a step.

`--device cuda` runs the same on a GPU (scripts/device-check.sh): model and batches on the device, the clock read
after `torch.cuda.synchronize()`.

Usage: .venv-bench/bin/python bench/offline_step_torch.py DATASET.parquet --algo bcql|bearl|cpq|coptidice|cdt
           [--steps N] [--threads T] [--warmup W] [--seed S] [--device cpu|cuda]
"""
import argparse
import contextlib
import json
import sys
import time
import types

import numpy as np
import pyarrow.parquet as pq
import torch

from columns import matrix

BATCH = 512
HIDDEN = [256, 256]
COMMON = dict(gamma=0.99, cost_limit=10, episode_len=200)  # OfflineCarRun-v0: 200 steps per episode
SCALES = dict(reward_scale=0.1, cost_scale=1.0)
ALGOS = {
    "bcql": (
        "BCQL",
        dict(vae_hidden_sizes=400, sample_action_num=10, tau=0.005, phi=0.05, lmbda=0.75, beta=0.5,
             PID=[0.1, 0.003, 0.001], num_q=2, num_qc=2),
        dict(actor_lr=1e-3, critic_lr=1e-3, vae_lr=1e-3),
    ),
    "bearl": (
        "BEARL",
        dict(vae_hidden_sizes=400, sample_action_num=10, tau=0.005, beta=0.5, lmbda=0.75, mmd_sigma=50,
             target_mmd_thresh=0.05, num_samples_mmd_match=10, PID=[0.1, 0.003, 0.001], kernel="gaussian",
             num_q=2, num_qc=2, start_update_policy_step=0),
        dict(actor_lr=1e-3, critic_lr=1e-3, alpha_lr=1e-3, vae_lr=1e-3),
    ),
    "cpq": (
        "CPQ",
        dict(vae_hidden_sizes=400, sample_action_num=10, tau=0.005, beta=0.5, num_q=2, num_qc=2, qc_scalar=1.5),
        dict(actor_lr=1e-4, critic_lr=1e-3, alpha_lr=1e-4, vae_lr=1e-3),
    ),
    "coptidice": (
        "COptiDICE",
        dict(f_type="softchi", alpha=0.5, cost_ub_epsilon=0.01, num_nu=2, num_chi=2),
        dict(actor_lr=1e-4, critic_lr=1e-4, scalar_lr=1e-4),
    ),
}


def stand_in_loggers():
    """Empty modules for what fsrl.utils imports at load time (wandb, TensorBoard) when they are not installed."""
    wanted = {
        "wandb": {},
        "torch.utils.tensorboard": {"SummaryWriter": None},
        "tensorboard.backend.event_processing.event_accumulator": {},
    }
    for name, attrs in wanted.items():
        try:
            __import__(name)
            continue
        except ImportError:
            pass
        parts = name.split(".")
        for i in range(1, len(parts) + 1):
            full = ".".join(parts[:i])
            if full not in sys.modules:
                sys.modules[full] = types.ModuleType(full)
            if i > 1:
                setattr(sys.modules[".".join(parts[:i - 1])], parts[i - 1], sys.modules[full])
        for key, value in attrs.items():
            setattr(sys.modules[name], key, value)


def load(path):
    """OSRL's dataset dict from a canonical or compact (committed starter) file."""
    table = pq.read_table(path)
    obs, _ = matrix(table, "observations")
    act, _ = matrix(table, "actions")
    if "next_observations" in table.column_names:
        next_obs, left_out = matrix(table, "next_observations")
    else:
        next_obs, left_out = np.full_like(obs, np.nan), np.ones(len(obs), dtype=bool)
    # The compact form leaves next_observations out where row t+1 of the same episode starts from it.
    rows = np.flatnonzero(left_out)
    if len(rows) and rows[-1] + 1 >= len(obs):
        sys.exit("the last row has no next observation")
    next_obs[rows] = obs[rows + 1]
    column = lambda n: table.column(n).to_numpy().astype(np.float32)  # noqa: E731
    return {
        "observations": obs, "next_observations": next_obs, "actions": act,
        "rewards": column("rewards"), "costs": column("costs"),
        "terminals": column("terminals"), "timeouts": column("timeouts"),
    }


def cdt_batches(d, rng, total, batch=2048, k=10):
    """Windows of k steps, as tensors in CDTTrainer.train_one_step's argument order."""
    done = np.logical_or(d["terminals"], d["timeouts"])
    ends = np.flatnonzero(done) + 1
    starts = np.concatenate([[0], ends[:-1]])
    cost_returns = np.array([d["costs"][a:b].sum() for a, b in zip(starts, ends)])
    weights = np.maximum(0.0, 70.0 - cost_returns)
    p = weights / weights.sum() if weights.sum() > 0 else None
    obs_dim, act_dim = d["observations"].shape[1], d["actions"].shape[1]
    out = []
    for _ in range(total):
        s = np.zeros((batch, k, obs_dim), np.float32)
        a = np.zeros((batch, k, act_dim), np.float32)
        r, c, m, cost = (np.zeros((batch, k), np.float32) for _ in range(4))
        t = np.zeros((batch, k), np.int64)
        ep_cost = np.zeros(batch, np.float32)
        for i, j in enumerate(rng.choice(len(starts), size=batch, p=p)):
            first, last = starts[j], ends[j]
            start = rng.integers(0, last - first)
            rows = np.arange(first + start, min(first + start + k, last))
            n = len(rows)
            rewards, costs = d["rewards"][first:last], d["costs"][first:last]
            s[i, :n], a[i, :n] = d["observations"][rows], d["actions"][rows]
            r[i, :n] = np.cumsum(rewards[::-1])[::-1][start:start + n] * 0.1
            c[i, :n] = np.cumsum(costs[::-1])[::-1][start:start + n]
            m[i, :n], cost[i, :n] = 1.0, d["costs"][rows]
            t[i] = np.arange(start, start + k)
            ep_cost[i] = cost_returns[j]
        out.append([torch.from_numpy(x) for x in (s, a, r, c, t, m, ep_cost, cost)])
    return out


def synchronize(device):
    """Waits for the GPU's queued work, so the clock measures it (a no-op on the CPU)."""
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def main():
    p = argparse.ArgumentParser()
    p.add_argument("dataset")
    p.add_argument("--algo", required=True, choices=sorted(ALGOS) + ["cdt"])
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu")
    p.add_argument("--cdt-batch", type=int, default=2048, help="CDT's batch (OSRL's 2048)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)

    stand_in_loggers()
    with contextlib.redirect_stdout(sys.stderr):  # OSRL prints that CDT's optional OApackage is missing
        import osrl
        import osrl.algorithms as algorithms
        from fsrl.utils import DummyLogger
        from osrl.common.dataset import TransitionDataset

    if args.algo == "cdt":
        return time_cdt(args, rng, algorithms, DummyLogger, osrl)
    data = TransitionDataset(load(args.dataset), state_init=args.algo == "coptidice", **SCALES)
    d = data.dataset
    state_dim, action_dim = d["observations"].shape[1], d["actions"].shape[1]
    model_name, model_kw, trainer_kw = ALGOS[args.algo]
    if args.algo == "coptidice":
        init_prop, obs_std, act_std = data.get_dataset_states()
        model_kw = dict(model_kw, init_state_propotion=init_prop, observations_std=obs_std, actions_std=act_std)
    model = getattr(algorithms, model_name)(
        state_dim=state_dim, action_dim=action_dim, max_action=1.0,  # CarRun's action box is [-1, 1]
        a_hidden_sizes=HIDDEN, c_hidden_sizes=HIDDEN, device=args.device, **COMMON, **model_kw,
    ).to(args.device)
    trainer = getattr(algorithms, model_name + "Trainer")(
        model, None, logger=DummyLogger(), device=args.device, **SCALES, **trainer_kw
    )

    keys = ["observations", "next_observations", "actions", "rewards", "costs", "done"]
    if args.algo == "coptidice":
        keys.append("is_init")
    scale = {"rewards": SCALES["reward_scale"], "costs": SCALES["cost_scale"]}
    total = args.warmup + args.steps
    indices = rng.integers(0, len(d["observations"]), size=(total, BATCH))
    started = time.perf_counter()
    batches = [[torch.from_numpy(d[k][idx] * scale.get(k, 1)).float().to(args.device) for k in keys]
               for idx in indices]
    batch_seconds = time.perf_counter() - started

    def step(batch):
        if args.algo == "coptidice":
            trainer.train_one_step(batch)
        else:
            trainer.train_one_step(*batch)

    for batch in batches[:args.warmup]:
        step(batch)
    synchronize(args.device)
    started = time.perf_counter()
    for batch in batches[args.warmup:]:
        step(batch)
    synchronize(args.device)
    seconds = time.perf_counter() - started
    print(json.dumps({
        "algo": args.algo, "steps": args.steps, "warmup": args.warmup, "seconds": seconds,
        "ms_per_step": 1000 * seconds / args.steps, "batch_ms_per_step": 1000 * batch_seconds / total,
        "threads": torch.get_num_threads(), "torch": torch.__version__, "osrl": osrl.__version__,
        "device": args.device,
    }))


def time_cdt(args, rng, algorithms, DummyLogger, osrl):
    d = load(args.dataset)
    state_dim, action_dim = d["observations"].shape[1], d["actions"].shape[1]
    model = algorithms.CDT(
        state_dim=state_dim, action_dim=action_dim, max_action=1.0, seq_len=10, episode_len=200, embedding_dim=128,
        num_layers=3, num_heads=8, attention_dropout=0.1, residual_dropout=0.1, embedding_dropout=0.1,
        time_emb=True, use_rew=True, use_cost=True, cost_transform=True, stochastic=True, init_temperature=0.1,
        target_entropy=-action_dim,
    )
    trainer = algorithms.CDTTrainer(
        model, None, logger=DummyLogger(), learning_rate=1e-4, weight_decay=1e-4, betas=(0.9, 0.999),
        clip_grad=0.25, lr_warmup_steps=500, reward_scale=0.1, cost_scale=1.0, loss_cost_weight=0.02,
        loss_state_weight=0.0, device=args.device,
    )
    model.to(args.device)
    total = args.warmup + args.steps
    started = time.perf_counter()
    batches = [[x.to(args.device) for x in b] for b in cdt_batches(d, rng, total, batch=args.cdt_batch)]
    batch_seconds = time.perf_counter() - started
    for batch in batches[:args.warmup]:
        trainer.train_one_step(*batch)
    synchronize(args.device)
    started = time.perf_counter()
    for batch in batches[args.warmup:]:
        trainer.train_one_step(*batch)
    synchronize(args.device)
    seconds = time.perf_counter() - started
    print(json.dumps({
        "algo": "cdt", "steps": args.steps, "warmup": args.warmup, "seconds": seconds,
        "ms_per_step": 1000 * seconds / args.steps, "batch_ms_per_step": 1000 * batch_seconds / total,
        "threads": torch.get_num_threads(), "torch": torch.__version__, "osrl": osrl.__version__,
        "device": args.device,
    }))


if __name__ == "__main__":
    main()
