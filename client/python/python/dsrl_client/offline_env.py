"""DSRL's environment interface, answered by a dsrl server.

Importing `dsrl_client` registers the 38 offline env ids with gymnasium, as `import dsrl` does, so DSRL code changes
one import line (`import dsrl` -> `import dsrl_client as dsrl`, and `dsrl.offline_env` -> `dsrl_client.offline_env`):

    env = gym.make("OfflineCarCircle-v0")          # server/version/cache_dir may be passed here
    data = env.get_dataset()                       # from the server, through the shared cache
    env.set_target_cost(20)
    data = env.pre_process_data(data, outliers_percent=0.05)   # the server's filters: DSRL's output, bit for bit
    env.get_normalized_score(reward_return, cost_return)

The environment steps the real simulator, the same adapter the server's workers host (`dsrl_sim`), created at the
first `reset`; without the simulator packages, `reset` raises `SimulatorMissing` naming what to install, and the
dataset methods still work.
"""
import gymnasium as gym
import numpy as np

from . import catalog, simulators
from .datasets import KEYS, Dataset, load_dataset


class OfflineEnv(gym.Env):
    """One benchmark task: its dataset, DSRL's filters, normalized scores, and its simulator."""

    metadata = {"render_modes": []}

    def __init__(self, task, version="latest", server=None, cache_dir=None, progress=True, max_episode_steps=None):
        info = catalog.task(task)
        # The horizon is enforced here rather than by gymnasium's TimeLimit wrapper (see register_all).
        self.max_episode_steps = int(max_episode_steps or info["max_episode_steps"])
        self._elapsed_steps = 0
        self.task = info["id"]
        self.simulator_env_id = info["simulator_env_id"]
        self.version, self.server, self.cache_dir, self.progress = version, server, cache_dir, progress
        self.max_episode_reward = info["max_episode_reward"]
        self.min_episode_reward = info["min_episode_reward"]
        self.max_episode_cost = info["max_episode_cost"]
        self.min_episode_cost = info["min_episode_cost"]
        self.cost_thresholds = list(info["cost_thresholds"])
        self.target_cost = None
        # The hosted datasets' observations are the pinned simulator's (obs_dim); actions are in [-1, 1] for every
        # task. The simulator's own spaces replace these once it is created.
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (info["obs_dim"],), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (info["act_dim"],), np.float32)
        self._simulator = None

    # --- DSRL's dataset interface -------------------------------------------------------------------------------

    def get_dataset(self, h5path=None):
        """The task's dataset (this env's `version`, default "latest") as DSRL's dict, from the server through the
        shared cache; or, with `h5path`, a local file in DSRL's HDF5 layout (needs h5py)."""
        if h5path is not None:
            data = _read_hdf5(h5path)
        else:
            data = load_dataset(self.task, self.version, server=self.server, cache_dir=self.cache_dir,
                                progress=self.progress)
        if data["observations"].shape[1:] != self.observation_space.shape:
            raise ValueError(f"Observation shape does not match env: {data['observations'].shape[1:]} vs "
                             f"{self.observation_space.shape}")
        if data["actions"].shape[1:] != self.action_space.shape:
            raise ValueError(f"Action shape does not match env: {data['actions'].shape[1:]} vs "
                             f"{self.action_space.shape}")
        return data

    def set_target_cost(self, target_cost):
        self.target_cost = target_cost
        self.epsilon = 1 if self.target_cost == 0 else 0

    def get_normalized_score(self, reward, cost):
        """DSRL's normalization: reward by the task's min/max episode reward, cost by the target cost (plus one
        when the target is 0)."""
        if self.target_cost is None:
            raise ValueError("Reference score not provided for env: call set_target_cost first")
        normalized_reward = (reward - self.min_episode_reward) / (self.max_episode_reward - self.min_episode_reward)
        normalized_cost = (cost + self.epsilon) / (self.target_cost + self.epsilon)
        return normalized_reward, normalized_cost

    def pre_process_data(self, data_dict, outliers_percent=None, noise_scale=None, inpaint_ranges=None,
                         epsilon=None, density=1.0, cbins=10, rbins=50, max_npb=5, min_npb=2, *, seed=0):
        """DSRL's `pre_process_data`, computed by the server on the version `data_dict` was served as; the result
        is the filtered version it hosts, equal bit for bit to DSRL's output (tested against DSRL's own code).

        `seed` (not in DSRL) seeds the density filter's sampling, which DSRL draws from Python's global `random`:
        the result equals DSRL's after `random.seed(seed)`. Outliers and observation noise use DSRL's fixed
        generator (PCG64 seeded 1234) as a freshly made DSRL env does. Errors come from the server as `DsrlError`
        (e.g. too few trajectories in the tempting corner for `outliers_percent`).
        """
        if not isinstance(data_dict, Dataset) or data_dict.version is None:
            raise TypeError("pre_process_data filters a dataset on the server: pass the dict returned by "
                            "env.get_dataset() or dsrl_client.load_dataset()")
        if data_dict.fingerprint() != data_dict._fingerprint:
            raise ValueError("this dataset dict was changed after it was served; the server filters the served "
                             f"version {data_dict.version[:12]}, so apply pre_process_data before changing it")
        if data_dict.filter is not None:
            raise ValueError(f"this dataset is already filtered ({data_dict.filter}); give all filters in one "
                             "pre_process_data call on the dataset from get_dataset()")
        parts = []
        if density != 1.0:
            if not density < 1.0:
                raise AssertionError("density should be less than 1.0")
            parts += [f"density={_number(density)}", f"cbins={int(cbins)}", f"rbins={int(rbins)}",
                      f"max_npb={int(max_npb)}", f"min_npb={int(min_npb)}", f"seed={int(seed)}"]
        if outliers_percent is not None:
            parts.append(f"outliers_percent={_number(outliers_percent)}")
        if inpaint_ranges is not None:
            # Several ranges are sent as given: the server explains why it takes exactly one.
            parts.append("inpaint=" + ";".join(":".join(_number(v) for v in r) for r in inpaint_ranges))
        if epsilon is not None:
            parts.append(f"epsilon={_number(epsilon)}")
        if outliers_percent is not None or epsilon is not None:
            if self.target_cost is None:
                raise AssertionError("Please set target cost using env.set_target_cost(target_cost) if you want "
                                     "to add outliers or change epsilon")
            parts.append(f"target_cost={_number(self.target_cost)}")
        if noise_scale is not None:
            parts.append(f"noise_scale={_number(noise_scale)}")
        if not parts:
            unchanged = Dataset(data_dict)
            unchanged.__dict__.update(data_dict.__dict__)
            return unchanged
        return load_dataset(data_dict.task, data_dict.version, filter=",".join(parts), server=self.server,
                            cache_dir=self.cache_dir, progress=self.progress)

    # --- the simulator ----------------------------------------------------------------------------------------

    def _simulator_env(self):
        if self._simulator is None:
            self._simulator = simulators.make(self.simulator_env_id)
            self.action_space = gym.spaces.Box(self._simulator.low.astype(np.float32),
                                               self._simulator.high.astype(np.float32), dtype=np.float32)
        return self._simulator

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        simulator = self._simulator_env()
        episode_seed = seed if seed is not None else int(self.np_random.integers(0, 2**31 - 1))
        self._elapsed_steps = 0
        return simulator.reset(episode_seed), {}

    def step(self, action):
        obs, reward, cost, terminated, truncated, _ = self._simulator_env().step(action)
        self._elapsed_steps += 1
        truncated = truncated or self._elapsed_steps >= self.max_episode_steps
        return obs, reward, terminated, truncated, {"cost": cost}

    def close(self):
        if self._simulator is not None:
            self._simulator.close()
            self._simulator = None


class OfflineEnvWrapper(gym.Wrapper):
    """DSRL's wrapper: optional Gaussian noise on observations (`set_noise_scale`), DSRL methods passed through."""

    def __init__(self, env):
        super().__init__(env)
        self.noise_scale = None

    def set_noise_scale(self, noise_scale):
        self.noise_scale = noise_scale

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        if self.noise_scale is not None:
            obs = obs + np.random.normal(0, self.noise_scale, obs.shape)
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if self.noise_scale is not None:
            obs = obs + np.random.normal(0, self.noise_scale, obs.shape)
        return obs, reward, terminated, truncated, info

    def __getattr__(self, name):
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self.env.unwrapped, name)


def wrap_env(env, state_mean=0.0, state_std=1.0, reward_scale=1.0):
    """DSRL's `wrap_env`: normalized observations and scaled rewards."""
    env = gym.wrappers.TransformObservation(env, lambda state: (state - state_mean) / state_std)
    if reward_scale != 1.0:
        env = gym.wrappers.TransformReward(env, lambda reward: reward_scale * reward)
    return env


def register_all():
    """Registers the 38 offline ids (e.g. `OfflineCarCircle-v0`) with gymnasium. `gym.make` returns the
    `OfflineEnv` itself, without gymnasium's wrappers: gymnasium 1.x wrappers no longer pass unknown attributes
    through, so DSRL's `env.get_dataset()` on a wrapped env would fail there. The env keeps its horizon itself."""
    for info in catalog.tasks():
        gym.register(id=info["id"], entry_point="dsrl_client.offline_env:OfflineEnv", kwargs={"task": info["id"]},
                     order_enforce=False, disable_env_checker=True)


def _number(value):
    """The shortest decimal that reads back as the same float (the server's canonical numbers)."""
    value = float(value)
    return repr(int(value)) if value.is_integer() and abs(value) < 1e15 else repr(value)


def _read_hdf5(path):
    try:
        import h5py
    except ImportError as e:
        raise ImportError("get_dataset(h5path=...) reads DSRL's HDF5 files with h5py: pip install h5py") from e
    data = Dataset()
    with h5py.File(path, "r") as f:
        for key in KEYS:
            data[key] = f[key][:]
    for key in ("observations", "next_observations", "actions", "rewards", "costs"):
        data[key] = data[key].astype(np.float32)
    return data
