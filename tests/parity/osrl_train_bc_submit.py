"""The second half of tests/parity/osrl_train_bc.sh: OSRL's BC checkpoint, as its train_bc.py saved it, exported
with dsrl_client.export_policy and scored by the leaderboard.

    python osrl_train_bc_submit.py LOGDIR TASK OUT_DIR       (DSRL_SERVER and DSRL_ADMIN_TOKEN in the environment)

Rebuilds OSRL's `BC` from the run's config.yaml exactly as train_bc.py does, loads `checkpoint/model.pt`, exports
its actor as `mlp_actor` (BC-All: one policy for every threshold), creates a user with the admin token, submits,
waits for the scores and prints one JSON line: OSRL's own evaluation of that checkpoint (progress.txt: its rollouts
in dsrl_client's env) beside the leaderboard's (held seeds, the task's three thresholds).
"""
import csv
import json
import os
import sys
import time
import urllib.request
from pathlib import Path

import torch
import yaml
from osrl.algorithms import BC

import dsrl_client


def main():
    logdir, task, out_dir = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
    checkpoints = sorted(logdir.rglob("checkpoint/model.pt"))
    if len(checkpoints) != 1:
        sys.exit(f"expected one checkpoint/model.pt under {logdir}, found {len(checkpoints)}")
    run = checkpoints[0].parent.parent
    cfg = yaml.safe_load(open(run / "config.yaml"))
    info = dsrl_client.task(task)
    state_dim = info["obs_dim"] + (1 if cfg["bc_mode"] == "multi-task" else 0)
    env = dsrl_client.OfflineEnv(task=task)
    model = BC(state_dim=state_dim, action_dim=info["act_dim"], max_action=float(env.action_space.high[0]),
               a_hidden_sizes=cfg["a_hidden_sizes"], episode_len=cfg["episode_len"], device="cpu")
    model.load_state_dict(torch.load(checkpoints[0], map_location="cpu")["model_state"])
    dsrl_client.export_policy(model.actor, task=task, architecture="mlp_actor", out_dir=out_dir)

    server, admin = os.environ["DSRL_SERVER"].rstrip("/"), os.environ["DSRL_ADMIN_TOKEN"]
    request = urllib.request.Request(f"{server}/v1/users", method="POST",
                                     data=json.dumps({"name": f"osrl-check-{int(time.time())}"}).encode(),
                                     headers={"Authorization": f"Bearer {admin}",
                                              "Content-Type": "application/json"})
    user = json.load(urllib.request.urlopen(request))
    started = time.monotonic()
    submission = dsrl_client.submit(out_dir, task=task, name=f"OSRL-train_bc-{cfg['update_steps']}-steps",
                                    token=user["token"], wait=True, timeout=3600)
    rows = list(csv.DictReader(open(run / "progress.txt"), delimiter="\t"))
    last = rows[-1] if rows else {}
    print(json.dumps({
        "task": task,
        "osrl_commit": os.environ.get("OSRL_COMMIT"),
        "update_steps": cfg["update_steps"],
        "seed": cfg["seed"],
        "osrl_evaluation": {k: float(v) for k, v in last.items() if k.startswith("eval/")},
        "leaderboard": {k: submission.get(k) for k in ("id", "state", "reason", "normalized_reward",
                                                        "normalized_cost", "safe")},
        "thresholds": [{k: t[k] for k in ("cost_threshold", "episodes", "mean_reward_return", "mean_cost_return",
                                          "normalized_reward", "normalized_cost")}
                       for t in submission.get("thresholds", [])],
        "scoring_seconds": round(time.monotonic() - started, 1),
    }))
    if submission.get("state") != "finished":
        sys.exit(f"the submission ended {submission.get('state')}: {submission.get('reason')}")


if __name__ == "__main__":
    main()
