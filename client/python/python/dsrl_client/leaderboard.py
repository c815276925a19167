"""Submitting a checkpoint folder to the leaderboard and waiting for its scores."""
import json
import os
import time

from . import _native


def submit(folder, *, task, name, token=None, server=None, wait=False, timeout=3600.0, poll=2.0):
    """Uploads `folder` (one `policy.json` + `policy.safetensors`, or one per `threshold-K/`) as a submission of
    `name` for `task`. token: default `$DSRL_TOKEN`. Returns the submission (dict); with `wait=True`, polls until
    it is finished, failed or cancelled and returns that. Raises `DsrlError` (duplicate, quota, invalid files...)."""
    token = token or os.environ.get("DSRL_TOKEN")
    if not token:
        raise ValueError("submitting needs a user token: pass token= or set DSRL_TOKEN")
    submission = json.loads(_native.submit(str(folder), task, name, token, server))
    if not wait:
        return submission
    deadline = time.monotonic() + timeout
    while submission.get("state") not in ("finished", "failed", "cancelled"):
        if time.monotonic() > deadline:
            raise TimeoutError(f"submission {submission['id']} is still {submission.get('state')} after {timeout} s")
        time.sleep(poll)
        submission = json.loads(_native.submission(int(submission["id"]), server))
    return submission
