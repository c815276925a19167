"""The 38 benchmark tasks (the catalog compiled into the client: ids, simulators, horizons, dimensions,
normalization constants, cost thresholds)."""
import difflib
import functools
import json

from . import _native


@functools.lru_cache(maxsize=None)
def _tasks():
    return tuple(json.loads(_native.catalog_json()))


def tasks():
    """Every task as a dict (`id`, `family`, `simulator_env_id`, `max_episode_steps`, `obs_dim`, `act_dim`,
    `min/max_episode_reward`, `min/max_episode_cost`, `cost_thresholds`, ...)."""
    return [dict(t) for t in _tasks()]


def task(task_id):
    for t in _tasks():
        if t["id"] == task_id:
            return dict(t)
    near = difflib.get_close_matches(task_id, [t["id"] for t in _tasks()], n=3)
    raise KeyError(f"unknown task {task_id!r}" + (f"; did you mean {', '.join(near)}?" if near else ""))
