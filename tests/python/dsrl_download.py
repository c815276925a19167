"""DSRL's own package (dsrl 0.1.0 from PyPI, unmodified) against a dsrl-server's `/download/{file}` route.

Only the host part of DSRL's URLs changes (`http://data.offline-saferl.org` -> SERVER); the paths and file names are
DSRL's `DATASET_URLS` as they are. Prints one JSON document:
- `heads`: for every name of DATASET_URLS, the status of a HEAD request and the served version (X-Dsrl-Version);
- `loaded`: DSRL's `OfflineEnv.get_dataset()` for NAME (download with its urlretrieve, load with its h5py code),
  compared array by array with the Parquet of the served version (fetched from the server's REST API);
- `truncated`: what DSRL does when the connection drops mid-file: a one-shot proxy relays the first 4096 bytes of
  the answer for TRUNCATED_NAME and closes; reports DSRL's exception, whether a file was left in DSRL's cache and
  whether DSRL's loader then takes it for a dataset.

Usage: dsrl_download.py SERVER DATASET_DIR NAME TRUNCATED_NAME
"""
import io
import json
import os
import socket
import sys
import threading
import urllib.request

server, dataset_dir, name, truncated_name = sys.argv[1:5]
os.environ["DSRL_DATASET_DIR"] = dataset_dir  # read by dsrl at import
os.environ["DSRL_SUPPRESS_IMPORT_ERROR"] = "1"  # the simulators are not installed; get_dataset does not need them

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402

import dsrl.offline_env as offline_env  # noqa: E402
from dsrl.infos import DATASET_URLS  # noqa: E402

OLD_HOST = "http://data.offline-saferl.org"


def moved(url, host):
    assert url.startswith(OLD_HOST + "/download/"), url
    return host + url[len(OLD_HOST):]


def head(url):
    request = urllib.request.Request(url, method="HEAD")
    try:
        with urllib.request.urlopen(request) as r:
            return {"status": r.status, "version": r.headers.get("X-Dsrl-Version"), "task": r.headers.get("X-Dsrl-Task"),
                    "length": int(r.headers["Content-Length"]), "etag": r.headers.get("ETag")}
    except urllib.error.HTTPError as e:
        # A HEAD answer has no body: the same GET says why.
        try:
            urllib.request.urlopen(url)
            message = None
        except urllib.error.HTTPError as g:
            message = json.load(g)["error"]["message"]
        return {"status": e.code, "version": None, "message": message}


def get_json(url):
    with urllib.request.urlopen(url) as r:
        return json.load(r)


class Env(offline_env.OfflineEnv):
    """DSRL's OfflineEnv with only the spaces get_dataset checks (no simulator)."""

    def __init__(self, url, obs_dim, act_dim):
        super().__init__(dataset_url=url)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (act_dim,), np.float32)


def matrix(table, column):
    values = table.column(column).combine_chunks()
    width = values.type.list_size
    return values.flatten().to_numpy(zero_copy_only=False).reshape(-1, width)


def compare(data, task, version):
    raw = urllib.request.urlopen(f"{server}/v1/datasets/{task}/versions/{version}/download").read()
    table = pq.read_table(io.BytesIO(raw))
    ours = {
        "observations": matrix(table, "observations"),
        "next_observations": matrix(table, "next_observations"),
        "actions": matrix(table, "actions"),
        "rewards": table.column("rewards").to_numpy(),
        "costs": table.column("costs").to_numpy(),
        "terminals": table.column("terminals").to_numpy(zero_copy_only=False),
        "timeouts": table.column("timeouts").to_numpy(zero_copy_only=False),
    }
    return {k: bool(np.array_equal(np.asarray(data[k]).astype(v.dtype), v)) for k, v in ours.items()}


def truncating_proxy(upstream, keep):
    """Accepts one connection, forwards the request upstream, relays `keep` bytes of the answer, then closes."""
    host, port = upstream.split("//")[1].split(":")
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)

    def serve():
        client, _ = listener.accept()
        request = client.recv(65536)
        with socket.create_connection((host, int(port))) as up:
            up.sendall(request)
            sent = 0
            while sent < keep:
                chunk = up.recv(min(65536, keep - sent))
                if not chunk:
                    break
                client.sendall(chunk)
                sent += len(chunk)
        client.close()
        listener.close()

    threading.Thread(target=serve, daemon=True).start()
    return f"http://127.0.0.1:{listener.getsockname()[1]}"


heads = {key: head(moved(url, server)) for key, url in DATASET_URLS.items()}

url = moved(DATASET_URLS[name], server)
served = heads[name]
file_name = url.rsplit("/", 1)[1]
task_id = served["task"]
manifest = get_json(f"{server}/v1/datasets/{task_id}/versions/{served['version']}")
env = Env(url, manifest["observation_space"]["dim"], manifest["action_space"]["dim"])
data = env.get_dataset()
cached = os.path.join(dataset_dir, file_name)
loaded = {
    "task": task_id,
    "rows": int(data["observations"].shape[0]),
    "cached_file": os.path.exists(cached),
    "cached_bytes": os.path.getsize(cached),
    "equal": compare(data, task_id, served["version"]),
}

# A fresh cache folder, as a user who has not downloaded the file yet.
fresh = os.path.join(dataset_dir, "fresh")
offline_env.set_dataset_path(fresh)
proxy = truncating_proxy(server, 4096)
truncated_url = moved(DATASET_URLS[truncated_name], proxy)
truncated_file = os.path.join(fresh, truncated_url.rsplit("/", 1)[1])
try:
    offline_env.download_dataset_from_url(truncated_url)
    error = None
except Exception as e:  # what DSRL's user sees
    error = type(e).__name__
left = os.path.exists(truncated_file)
try:
    Env(truncated_url, manifest["observation_space"]["dim"], manifest["action_space"]["dim"]).get_dataset()
    taken = "loaded"
except Exception as e:
    taken = type(e).__name__
truncated = {"error": error, "file_left": left, "bytes_left": os.path.getsize(truncated_file) if left else 0,
             "load_after": taken}

print(json.dumps({"heads": heads, "loaded": loaded, "truncated": truncated}))
