"""dsrl from Python: the service's datasets, DSRL's filters and the leaderboard, and a drop-in for DSRL.

    import dsrl_client
    data = dsrl_client.load_dataset("OfflineCarCircle-v0", filter="noise=0.05")   # DSRL's keys and dtypes

    import gymnasium as gym
    import dsrl_client as dsrl            # was: import dsrl  (registers the 38 offline env ids)
    env = gym.make("OfflineCarCircle-v0")
    data = env.get_dataset()

Fetching is the Rust client's (`dsrl-client fetch`): sha256-verified, resumable, cached in `$DSRL_DATASET_DIR` or
`~/.dsrl/datasets`, shared with the CLI. The server is `$DSRL_SERVER` (default http://127.0.0.1:7070) unless given.
"""
from ._native import DsrlError, default_cache_dir, default_server
from .catalog import task, tasks
from .datasets import Dataset, StarterDataset, fetch, load_dataset, read_parquet
from .export import export_arrays, export_policy
from .leaderboard import submit, watch
from .offline_env import OfflineEnv, OfflineEnvWrapper, register_all, wrap_env
from .simulators import SimulatorMissing
from .uploads import upload

__all__ = ["DsrlError", "Dataset", "OfflineEnv", "OfflineEnvWrapper", "SimulatorMissing", "StarterDataset",
           "default_cache_dir", "default_server", "export_arrays", "export_policy", "fetch", "load_dataset",
           "read_parquet", "submit", "upload", "task", "tasks", "watch", "wrap_env"]

register_all()
