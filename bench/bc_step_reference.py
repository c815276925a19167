"""NumPy reference for bench/bc_step.sh: OSRL's BC update (MLPActor [obs, 256, 256, act], ReLU, tanh output; MSE;
Adam lr 1e-3; batches of 512 drawn uniformly with replacement) written by hand in float32 NumPy/OpenBLAS: the
arithmetic floor of the update without a framework, shown beside PyTorch for scale. Prints one JSON line.

Usage: python bench/bc_step_reference.py DATASET.parquet --steps N
"""
import argparse
import json
import time

import numpy as np
import pyarrow.parquet as pq

from columns import matrix


def main():
    p = argparse.ArgumentParser()
    p.add_argument("dataset")
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    table = pq.read_table(args.dataset, columns=["observations", "actions"])
    obs = matrix(table, "observations")[0]
    act = matrix(table, "actions")[0]
    rng = np.random.default_rng(args.seed)
    sizes = [obs.shape[1], 256, 256, act.shape[1]]
    params = []
    for i, o in zip(sizes[:-1], sizes[1:]):
        params += [rng.standard_normal((i, o)).astype(np.float32) / np.sqrt(i), np.zeros(o, np.float32)]
    m = [np.zeros_like(p) for p in params]
    v = [np.zeros_like(p) for p in params]
    lr, b1, b2, eps = 1e-3, 0.9, 0.999, 1e-8

    def step(t):
        idx = rng.integers(0, len(obs), 512)
        x, y = obs[idx], act[idx]
        w1, c1, w2, c2, w3, c3 = params
        h1 = np.maximum(x @ w1 + c1, 0)
        h2 = np.maximum(h1 @ w2 + c2, 0)
        out = np.tanh(h2 @ w3 + c3)
        diff = out - y
        loss = float(np.mean(diff * diff))
        g_out = (2.0 / diff.size) * diff * (1 - out * out)
        g_w3, g_c3 = h2.T @ g_out, g_out.sum(0)
        g_h2 = (g_out @ w3.T) * (h2 > 0)
        g_w2, g_c2 = h1.T @ g_h2, g_h2.sum(0)
        g_h1 = (g_h2 @ w2.T) * (h1 > 0)
        g_w1, g_c1 = x.T @ g_h1, g_h1.sum(0)
        for k, g in enumerate([g_w1, g_c1, g_w2, g_c2, g_w3, g_c3]):
            m[k] = b1 * m[k] + (1 - b1) * g
            v[k] = b2 * v[k] + (1 - b2) * g * g
            params[k] -= lr * (m[k] / (1 - b1**t)) / (np.sqrt(v[k] / (1 - b2**t)) + eps)
        return loss

    for t in range(1, 51):  # warm-up
        step(t)
    started = time.perf_counter()
    for t in range(51, 51 + args.steps):
        loss = step(t)
    seconds = time.perf_counter() - started
    print(json.dumps({"steps": args.steps, "seconds": seconds, "ms_per_step": 1000 * seconds / args.steps, "final_mse": loss}))


if __name__ == "__main__":
    main()
