"""Datasets from a dsrl server as DSRL's dictionaries of NumPy arrays.

`load_dataset` fetches through the client crate (`dsrl_client._native`, the same code as `dsrl-client fetch`):
verified by sha256, resumable, into `$DSRL_DATASET_DIR` or `~/.dsrl/datasets`, so a version fetched by the CLI is
found here and the other way round. A full version id that is complete in the cache needs no server at all.
"""
import hashlib
import json
import warnings

import numpy as np

from . import _native

KEYS = ("observations", "next_observations", "actions", "rewards", "costs", "terminals", "timeouts")


class Dataset(dict):
    """DSRL's dataset dictionary (the seven keys, float32 arrays and bool flags), which also knows where it came
    from: `task`, `version` (sha256 of the served Parquet file), `filter` (the canonical filter it was derived with,
    or None), `path` (the cached Parquet file) and `manifest` (as served). `pre_process_data` needs these to ask
    the server for the filtered version."""

    task = None
    version = None
    filter = None
    path = None
    manifest = None
    _fingerprint = None

    def fingerprint(self):
        """A digest of the returns-defining arrays and of the arrays' identities: `pre_process_data` refuses a
        dictionary changed since it was served, because the server filters the served version, not the change."""
        digest = hashlib.sha256()
        for key in KEYS:
            array = self.get(key)
            digest.update(key.encode())
            if array is None:
                digest.update(b"missing")
                continue
            digest.update(repr((id(array), array.shape, str(array.dtype))).encode())
            if key in ("rewards", "costs", "terminals", "timeouts"):
                digest.update(np.ascontiguousarray(array).tobytes())
        return digest.hexdigest()


def fetch(task, version="latest", filter=None, server=None, cache_dir=None, progress=True):
    """Makes a version complete and verified in the cache; returns the fetch report (a dict with `path`,
    `version`, `cache_hit`, `downloaded_bytes`, `resumed_from`, `manifest`, ...). Raises `DsrlError`."""
    return json.loads(_native.fetch(task, version, filter, server, None if cache_dir is None else str(cache_dir),
                                    progress))


def read_parquet(path):
    """All columns of a dataset file as DSRL's arrays (writable, no copy beyond the one out of Parquet)."""
    data = {}
    for key, buffer, shape, dtype in _native.read_dataset(str(path)):
        data[key] = np.frombuffer(buffer, dtype=np.dtype(dtype)).reshape(shape)
    return data


class StarterDataset(UserWarning):
    """The dataset served is the task's starter, a cut of its build, not the paper-size dataset."""


def load_dataset(task, version="latest", filter=None, server=None, cache_dir=None, progress=True):
    """`task`'s dataset as DSRL's dict: `observations` (N, obs_dim) float32, `next_observations`, `actions`
    (N, act_dim), `rewards`, `costs` (N,) float32, `terminals`, `timeouts` (N,) bool.

    version: a version id (sha256), a tag, or "latest". filter: a DSRL filter in the server's syntax, e.g.
    "noise=0.05" or "density=0.5,seed=0" (see `dsrl-client fetch --help`); the server derives and hosts the
    filtered version. server: default `$DSRL_SERVER`, else http://127.0.0.1:7070.
    """
    report = fetch(task, version, filter, server, cache_dir, progress)
    dataset = Dataset(read_parquet(report["path"]))
    dataset.task = report["task"]
    dataset.version = report["version"]
    dataset.path = report["path"]
    dataset.manifest = report.get("manifest")
    # A server that hosts only the committed starter says so, naming the command that builds the full dataset.
    notice = ((dataset.manifest or {}).get("hosting") or {}).get("notice")
    if notice:
        warnings.warn(notice, StarterDataset, stacklevel=2)
    provenance = (dataset.manifest or {}).get("provenance") or {}
    dataset.filter = provenance.get("filter") if provenance.get("kind") == "filter" else None
    dataset._fingerprint = dataset.fingerprint()
    return dataset
