"""PyTorch reference for bench/bc_step.sh: OSRL's BC update as OSRL writes it (osrl/algorithms/bc.py, spec 5.5):
MLPActor [obs, 256, 256, act] with ReLU and tanh output, MSE loss, torch.optim.Adam lr 1e-3, batches of 512 drawn
uniformly with replacement, on the CPU or a GPU (--device cuda: the data is uploaded once, batches are drawn on the
GPU, and the timer synchronizes). Prints one JSON line.

Usage: .venv-bench/bin/python bench/bc_step_torch.py DATASET.parquet --steps N [--threads 1] [--device cuda]
"""
import argparse
import json
import time

import numpy as np
import pyarrow.parquet as pq
import torch

from columns import matrix


def main():
    p = argparse.ArgumentParser()
    p.add_argument("dataset")
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    table = pq.read_table(args.dataset, columns=["observations", "actions"])
    obs = torch.from_numpy(matrix(table, "observations")[0])
    act = torch.from_numpy(matrix(table, "actions")[0])
    device = torch.device(args.device)
    obs, act = obs.to(device), act.to(device)
    sizes = [obs.shape[1], 256, 256, act.shape[1]]
    layers = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers += [torch.nn.Linear(a, b), torch.nn.ReLU() if i < len(sizes) - 2 else torch.nn.Tanh()]
    actor = torch.nn.Sequential(*layers).to(device)
    optim = torch.optim.Adam(actor.parameters(), lr=1e-3)

    def step():
        idx = torch.randint(0, len(obs), (512,), device=device)
        loss = torch.nn.functional.mse_loss(actor(obs[idx]), act[idx])
        optim.zero_grad()
        loss.backward()
        optim.step()
        return loss.item()

    for _ in range(50):  # warm-up
        step()
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    sync()
    started = time.perf_counter()
    for _ in range(args.steps):
        loss = step()
    sync()
    seconds = time.perf_counter() - started
    print(json.dumps({
        "steps": args.steps, "seconds": seconds, "ms_per_step": 1000 * seconds / args.steps, "final_mse": loss,
        "torch": torch.__version__, "threads": torch.get_num_threads(), "device": str(device),
    }))


if __name__ == "__main__":
    main()
