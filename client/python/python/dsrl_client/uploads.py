"""Uploading a dataset file to a dsrl server (the admin's side of hosting: `dsrl-client admin ingest` in Python)."""
import json
import os

from . import _native


def upload(path, *, task, token=None, server=None, tags=(), observation_space=None, license=None,
           keep_latest=False, progress=True):
    """Uploads `path` (a Parquet file, or a DSRL HDF5 file) as a version of `task` and returns the server's answer
    (dict: `created`, `version`, `moved_tags`, `manifest_url`, `download_url`).

    token: the server's admin token, default `$DSRL_ADMIN_TOKEN`. tags: more tags to point at the version (`latest`
    moves to it unless `keep_latest`). observation_space: `"paper"` for MetaDrive files in the paper's 261-feature
    space. A paper-size file takes the server minutes to convert: the call waits for as long as the server is
    working on it, and calling again with the same file follows that conversion (or returns the version already
    made, `created=False`) rather than sending the bytes again. Raises `DsrlError` with the server's code
    (`permission_denied`, `too_large`, `invalid_dataset`, ...) or the client's (`timeout`, `unreachable`, `io`)."""
    token = token or os.environ.get("DSRL_ADMIN_TOKEN")
    if not token:
        raise ValueError("uploading needs the server's admin token: pass token= or set DSRL_ADMIN_TOKEN")
    answer = _native.ingest(task, str(path), token, server, list(tags), observation_space, license,
                            keep_latest, progress)
    return json.loads(answer)
