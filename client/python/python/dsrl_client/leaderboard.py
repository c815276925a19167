"""Submitting a checkpoint folder to the leaderboard and waiting for its scores."""
import json
import os
import time

from . import _native


def submit(folder, *, task, name, token=None, server=None, wait=False, timeout=3600.0, poll=5.0):
    """Uploads `folder` (one `policy.json` + `policy.safetensors`, or one per `threshold-K/`) as a submission of
    `name` for `task`. token: default `$DSRL_TOKEN`. Returns the submission (dict); with `wait=True`, waits until
    it is finished, failed or cancelled (at most `timeout` seconds) and returns that: each request asks the server
    to answer when the submission ends or after `poll` seconds (1-60). Raises `DsrlError` (duplicate, quota,
    invalid files...)."""
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
        left = deadline - time.monotonic()
        wait_seconds = max(1, min(60, int(poll), int(left) + 1))
        submission = json.loads(_native.submission(int(submission["id"]), server, wait_seconds))
    return submission


def watch(submission, *, threshold, episode=0, gif=None, server=None, wait=False, timeout=600.0, poll=2.0):
    """A scored episode of `submission` (its id) at `threshold`, replayed by the server from its held seed with the
    submitted policy: a dict with the episode's seed, returns, length and every step's reward and cost (`steps`), the
    same as `dsrl-client watch`. The server makes a replay on the first request and while it waits for scoring to be
    idle; until then this returns None, or with `wait=True` polls until it is made. `gif=PATH` also writes the
    episode's animated GIF there. Raises `DsrlError` for an episode the submission did not play (not_found) or a
    submission whose checkpoint the server does not hold."""
    deadline = time.monotonic() + timeout
    while True:
        replay = _native.episode_replay(int(submission), float(threshold), int(episode), server)
        if replay is not None:
            break
        if not wait:
            return None
        if time.monotonic() > deadline:
            raise TimeoutError(f"the replay of submission {submission}'s episode {episode} at threshold {threshold} "
                               f"is still queued after {timeout} s")
        time.sleep(poll)
    replay = json.loads(replay)
    if gif is not None:
        with open(gif, "wb") as f:
            f.write(_native.episode_replay_gif(int(submission), float(threshold), int(episode), server))
    return replay
