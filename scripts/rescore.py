#!/usr/bin/env python3
"""Scores checkpoints again on a fresh server of a given build and compares every episode with a recorded scoring:
the check that a change on the scoring path left every score as it was (evaluation/scoring_path.sha256 is renewed
without bumping SCORER_REVISION only when this finds no difference).

The held episode seeds come from a server's secret, so the fresh server is given the secret of the server that
scored the recording (`--secret`, a data folder's `evaluation-secret`); reference import is off (the imported
entries would hold the same checkpoints), and the server has two local simulator workers, as the default does. A
checkpoint names the dataset version it was trained on, which the server must host: it hosts the committed starters,
and a recorded entry's other version (a full build) is uploaded from the client's cache (`$DSRL_DATASET_DIR`,
default ~/.dsrl/datasets, where the sweep fetched it).

    # against committed reference entries (their checkpoints from the sweep's state folder):
    scripts/rescore.py --bin ~/.cache/dsrl/target/release --secret ~/.dsrl/reference-full/server/evaluation-secret \
        --results data/reference/full_builds.jsonl --policies ~/.dsrl/reference-full/policies OfflineBallRun-v0
    # one build against another (any checkpoints): run each with --out, then compare with --against
    scripts/rescore.py --bin OLD --secret S --out old.json OfflinePointGoal1Gymnasium-v0:ckpt/bc-all
    scripts/rescore.py --bin NEW --secret S --against old.json OfflinePointGoal1Gymnasium-v0:ckpt/bc-all

Positional arguments: `TASK:DIR` (a checkpoint folder as `dsrl-client submit` takes it), or with --results and
--policies, task ids whose recorded entries' checkpoints are found under `<policies>/<task>/seed-<s>/<method>`.
Exits 1 when any episode differs, 2 on bad arguments; prints one line per checkpoint.
"""
import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request

# The reference results' method names and the sweep's folder names for them (dsrl-admin reference: pipeline/reference/src/plan.rs).
FOLDERS = {"BC-All": "bc-all", "BC-Safe": "bc-safe", "CDT": "cdt", "BCQ-Lag": "bcql", "BEAR-Lag": "bearl",
           "CPQ": "cpq", "COptiDICE": "coptidice", "CAPS": "caps",
           "FISOR": "fisor", "LSPC": "lspc"}
FIELDS = ("cost_threshold", "episode", "reward_return", "cost_return", "length")


def episodes_key(episodes):
    return sorted(tuple(e[f] for f in FIELDS) for e in episodes)


def get(url):
    with urllib.request.urlopen(url, timeout=60) as r:
        return json.load(r)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bin", required=True, help="folder with dsrl-server, dsrl-client and dsrl-sim-worker")
    parser.add_argument("--secret", required=True, help="the recording server's evaluation-secret file")
    parser.add_argument("--results", help="a reference results file (.jsonl) whose episodes are expected")
    parser.add_argument("--policies", help="the sweep's policies folder (with --results)")
    parser.add_argument("--against", help="another run's --out file whose episodes are expected")
    parser.add_argument("--out", help="write {task: {checkpoint_sha256: episodes}} here")
    parser.add_argument("--timeout", type=float, default=3600, help="seconds to wait for each scoring")
    parser.add_argument("checkpoints", nargs="+")
    args = parser.parse_args()

    def fail(message):
        print(f"rescore: {message}", file=sys.stderr)
        sys.exit(2)

    for name in ("dsrl-server", "dsrl-client", "dsrl-sim-worker"):
        if not os.access(os.path.join(args.bin, name), os.X_OK):
            fail(f"no {name} in {args.bin}")
    if not os.path.isfile(args.secret):
        fail(f"no secret file {args.secret}")
    if bool(args.results) != bool(args.policies):
        fail("--results and --policies go together")
    expected = {}  # (task, checkpoint_sha256) -> episodes
    jobs = []  # (task, folder, label)
    needed = set()  # (task, dataset version) the recorded entries were trained on
    if args.results:
        entries = [json.loads(line) for line in open(args.results) if line.strip()]
        for task in args.checkpoints:
            found = [e for e in entries if e["task"] == task]
            if not found:
                fail(f"{args.results} has no entry of {task}")
            for e in found:
                folder = os.path.join(args.policies, task, f"seed-{e['seed']}", FOLDERS[e["method"]])
                if not os.path.isdir(folder):
                    print(f"{task} {e['method']} seed {e['seed']}: no checkpoints at {folder}, skipped")
                    continue
                expected[(task, e["checkpoint_sha256"])] = e["episodes"]
                needed.add((task, e["dataset_version"]))
                jobs.append((task, folder, f"{e['method']} seed {e['seed']}"))
    else:
        for spec in args.checkpoints:
            task, _, folder = spec.partition(":")
            if not folder or not os.path.isdir(folder):
                fail(f"{spec}: expected TASK:DIR with DIR a checkpoint folder")
            jobs.append((task, folder, folder))
    if args.against:
        for task, by_digest in json.load(open(args.against)).items():
            for digest, episodes in by_digest.items():
                expected[(task, digest)] = episodes

    work = tempfile.mkdtemp(prefix="dsrl-rescore.")
    data = os.path.join(work, "server")
    os.makedirs(data)
    shutil.copy(args.secret, os.path.join(data, "evaluation-secret"))
    env = dict(os.environ, DSRL__SIMULATORS__LOCAL_WORKERS="2", DSRL__LEADERBOARD__SUBMISSIONS_PER_DAY="100000",
               DSRL__LEADERBOARD__IMPORT_REFERENCE_RESULTS="false")
    out = open(os.path.join(work, "server.out"), "w+")
    server = subprocess.Popen([os.path.join(args.bin, "dsrl-server"), "--listen", "127.0.0.1:0", "--data-dir", data],
                              stdout=out, stderr=open(os.path.join(work, "server.log"), "w"), env=env)
    try:
        url = None
        for _ in range(600):
            out.seek(0)
            for line in out.read().splitlines():
                if line.startswith("dsrl-server listening on "):
                    url = line.split()[-1]
            if url:
                break
            time.sleep(0.1)
        if not url:
            fail(f"the server did not start (log: {work}/server.log)")
        for _ in range(1200):
            if get(f"{url}/v1/simulators").get("healthy_workers") == 2:
                break
            time.sleep(0.25)
        client = os.path.join(args.bin, "dsrl-client")
        admin = open(os.path.join(data, "admin-token")).read().strip()
        token = subprocess.run([client, "--server", url, "admin", "create-user", "rescore"], check=True,
                               capture_output=True, text=True,
                               env=dict(os.environ, DSRL_ADMIN_TOKEN=admin)).stdout.strip()
        cache = os.environ.get("DSRL_DATASET_DIR", os.path.expanduser("~/.dsrl/datasets"))
        for task, version in sorted(needed):
            hosted = [v["version"] for v in get(f"{url}/v1/datasets/{task}/versions")["versions"]]
            if version in hosted:
                continue
            folder = os.path.join(cache, task, version)
            files = sorted(f for f in os.listdir(folder) if f.endswith(".parquet")) if os.path.isdir(folder) else []
            if not files:
                fail(f"{task}: version {version[:12]} is neither a starter nor in the cache ({folder})")
            subprocess.run([client, "--server", url, "admin", "ingest", "--task", task, "--keep-latest",
                            os.path.join(folder, files[0])], check=True, capture_output=True,
                           env=dict(os.environ, DSRL_ADMIN_TOKEN=admin))
        scored, differing = {}, 0
        for task, folder, label in jobs:
            submitted = subprocess.run([client, "--server", url, "--json", "submit", folder, "--task", task, "--name",
                                        f"rescore-{len(jobs)}-{sum(len(v) for v in scored.values())}"], capture_output=True, text=True,
                                       env=dict(os.environ, DSRL_TOKEN=token))
            if submitted.returncode != 0:
                fail(f"{task} {label}: submit failed: {submitted.stderr.strip()}")
            sid = json.loads(submitted.stdout)["id"]
            deadline = time.monotonic() + args.timeout
            while True:
                view = get(f"{url}/v1/submissions/{sid}")
                if view["state"] == "finished":
                    break
                if view["state"] in ("failed", "cancelled") or time.monotonic() > deadline:
                    fail(f"{task} {label}: submission {sid} {view['state']}: {view.get('reason')}")
                time.sleep(0.5)
            digest = view["checkpoint_sha256"]
            scored.setdefault(task, {})[digest] = view["episodes"]
            recorded = expected.get((task, digest))
            if recorded is None:
                verdict = "scored (nothing recorded to compare with)"
            elif episodes_key(recorded) == episodes_key(view["episodes"]):
                verdict = f"identical ({len(recorded)} episodes)"
            else:
                differing += 1
                pairs = zip(episodes_key(recorded), episodes_key(view["episodes"]))
                first = next(((a, b) for a, b in pairs if a != b), None)
                verdict = f"DIFFERS: first recorded/now {first}"
            print(f"{task} {label} ({digest[:12]}): {verdict}", flush=True)
        if args.out:
            json.dump(scored, open(args.out, "w"))
        sys.exit(1 if differing else 0)
    finally:
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
