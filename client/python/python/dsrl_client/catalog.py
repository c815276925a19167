"""The 38 benchmark tasks (the catalog compiled into the client: ids, simulators, horizons, dimensions,
normalization constants, cost thresholds)."""
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
    """One task; an unknown id raises KeyError naming the catalog's nearest ids (the server's suggestions)."""
    return json.loads(_native.task_json(task_id))
