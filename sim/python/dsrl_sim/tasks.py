"""The benchmark tasks' simulators behind one interface.

    env = make_env("SafetyBallRun-v0")
    obs = env.reset(seed)                       # float32 observation
    obs, reward, cost, terminated, truncated = env.step(action)

Bullet-Safety-Gym tasks come from gymnasium's registry (cost in info["cost"]); Safety-Gymnasium tasks from
safety_gymnasium.make (cost is the third return value); SafeMetaDrive from metadrive_tasks (cost in info["cost"]).
Actions are clipped to the action space before stepping: the worker's documented policy for out-of-range actions.
"""
import importlib.metadata
import os
import random

import numpy as np

BULLET = "bullet-safety-gym"
SAFETY_GYMNASIUM = "safety-gymnasium"
METADRIVE = "metadrive"


def family(sim_id):
    if sim_id.startswith("SafeMetaDrive-"):
        return METADRIVE
    agent_task = sim_id[len("Safety"):-len("-v0")] if sim_id.endswith("-v0") else ""
    if any(agent_task == a + t for a in ("Ant", "Ball", "Car", "Drone") for t in ("Run", "Circle")):
        return BULLET
    return SAFETY_GYMNASIUM


def simulator_version(fam):
    package = {BULLET: "bullet-safety-gym", SAFETY_GYMNASIUM: "safety-gymnasium", METADRIVE: "metadrive-simulator"}[fam]
    return f"{package} {importlib.metadata.version(package)}"


_NUMPY_DRAWS = ("uniform", "randint", "rand", "randn", "random", "random_sample", "normal", "choice", "shuffle",
                "permutation")
_PYTHON_DRAWS = ("uniform", "random", "randint", "randrange", "choice", "shuffle", "gauss", "sample")
_GLOBAL_DRAWS = [(np.random, name, getattr(np.random, name)) for name in _NUMPY_DRAWS] + [
    (random, name, getattr(random, name)) for name in _PYTHON_DRAWS]


class _GlobalRandomState:
    """Bullet-Safety-Gym ignores `reset(seed=...)` and draws from the process-global `np.random` and `random`
    (start positions, orientations, joint noise), looking the functions up at each call. Each env owns a seeded
    RandomState and Random and points those module functions at them around its calls, so an env's episodes depend
    only on its own seed, whatever other envs in the process do. (Swapping the global states with get_state and
    set_state instead costs ~116 us per call, more than a Bullet step.)"""

    def __init__(self, seed):
        numpy_draws, python_draws = np.random.RandomState(seed), random.Random(seed)
        self.patch = [(np.random, name, getattr(numpy_draws, name)) for name in _NUMPY_DRAWS] + [
            (random, name, getattr(python_draws, name)) for name in _PYTHON_DRAWS]

    def __enter__(self):
        for module, name, draw in self.patch:
            setattr(module, name, draw)

    def __exit__(self, *exc):
        for module, name, draw in _GLOBAL_DRAWS:
            setattr(module, name, draw)
        return False


class Env:
    def __init__(self, sim_id, controller=None):
        self.sim_id = sim_id
        self.family = family(sim_id)
        if controller and self.family != METADRIVE:
            raise ValueError(f"{sim_id}: only MetaDrive tasks take a controller")
        self.controlled = bool(controller)
        if self.family == BULLET:
            import gymnasium
            import bullet_safety_gym  # noqa: F401  (registers the tasks)

            from . import speedups

            speedups.apply_bullet_safety_gym()
            self._env = gymnasium.make(sim_id)
            self.max_episode_steps = self._env.spec.max_episode_steps
        elif self.family == SAFETY_GYMNASIUM:
            import safety_gymnasium

            from . import speedups

            speedups.apply_safety_gymnasium()
            self._env = safety_gymnasium.make(sim_id)
            self.max_episode_steps = self._env.spec.max_episode_steps
        else:
            from . import metadrive_tasks

            self._env = metadrive_tasks.make(sim_id, controller)
            self.max_episode_steps = metadrive_tasks.HORIZON
        space = self._env.action_space
        self.low = np.asarray(space.low, dtype=np.float64)
        self.high = np.asarray(space.high, dtype=np.float64)
        self.act_dim = int(np.prod(space.shape))
        self.obs_dim = int(np.prod(self._env.observation_space.shape))

    def reset(self, seed, switch=None):
        if switch:
            if not self.controlled:
                raise ValueError(f"{self.sim_id}: only an env built with a controller can switch it")
            self._env.set_controller(switch)
        if self.family == BULLET:
            self._random = _GlobalRandomState(int(seed) % 2**32)
            with self._random:
                obs, _ = self._env.reset(seed=int(seed))
        else:
            obs, _ = self._env.reset(seed=int(seed))
        return np.asarray(obs, dtype=np.float32).reshape(-1)

    def step(self, action):
        """-> observation, reward, cost, terminated, truncated, and the action the simulator applied (the clipped
        action, or the controller's)."""
        # np.minimum/np.maximum: the same result as np.clip at a sixth of its call cost on tiny arrays.
        action = np.minimum(np.maximum(np.asarray(action, dtype=np.float64), self.low), self.high)
        if self.family == SAFETY_GYMNASIUM:
            obs, reward, cost, terminated, truncated, _ = self._env.step(action)
        elif self.family == BULLET:
            with self._random:
                obs, reward, terminated, truncated, info = self._env.step(action)
            cost = info["cost"]
        else:
            obs, reward, terminated, truncated, info = self._env.step(action)
            cost = info["cost"]
            if self.controlled:
                action = np.asarray(info["raw_action"], dtype=np.float64)
        return (np.asarray(obs, dtype=np.float32).reshape(-1), float(reward), float(cost), bool(terminated),
                bool(truncated), action)

    def frame(self, width, height):
        """An RGB image of the environment as it is now, uint8 [height, width, 3], drawn without a display. Drawing
        reads the simulator's state and changes none of it, so an episode is the same with or without frames."""
        if self.family == SAFETY_GYMNASIUM:
            return _mujoco_frame(self._env.unwrapped, width, height)
        if self.family == BULLET:
            return _bullet_frame(self._env.unwrapped, width, height)
        # MetaDrive's top-down view (pygame on SDL's dummy video driver), centred on the ego vehicle.
        os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
        image = self._env.render(mode="topdown", window=False, screen_size=(width, height))
        return np.ascontiguousarray(np.asarray(image, dtype=np.uint8)[:height, :width, :3])

    def close(self):
        self._env.close()


def _mujoco_frame(builder, width, height):
    """Safety-Gymnasium's tracking camera through MuJoCo's EGL context (Mesa's software rasterizer where there is
    no GPU), shadows and reflections off: ~50 ms a frame at 160 x 160 on one core instead of ~95."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    import mujoco
    from safety_gymnasium.builder import RenderConf

    builder.render_parameters = RenderConf("rgb_array", int(width), int(height), None, "track")
    viewer = getattr(builder.task, "viewer", None)
    if viewer is not None:
        for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION):
            viewer.scn.flags[flag] = 0
    return np.ascontiguousarray(np.asarray(builder.render(), dtype=np.uint8)[:, :, :3])


def _bullet_frame(env, width, height):
    """pybullet's software renderer (ER_TINY_RENDERER: no OpenGL), looking down at the agent from behind."""
    import pybullet

    target = list(env.agent.get_position())
    view = env.bc.computeViewMatrixFromYawPitchRoll(cameraTargetPosition=target, distance=8.0, yaw=-90.0,
                                                    pitch=-60.0, roll=0.0, upAxisIndex=2)
    projection = env.bc.computeProjectionMatrixFOV(fov=60.0, aspect=width / height, nearVal=0.1, farVal=100.0)
    _, _, pixels, _, _ = env.bc.getCameraImage(width=int(width), height=int(height), viewMatrix=view,
                                                projectionMatrix=projection, renderer=pybullet.ER_TINY_RENDERER)
    return np.ascontiguousarray(np.asarray(pixels, dtype=np.uint8).reshape(height, width, 4)[:, :, :3])


def drive(env):
    """Plays `env`'s current episode to its end with the actions ignored (its controller drives), calling `step`
    exactly as a client's steps would. -> observations float32 [T, obs_dim], applied actions float32 [T, act_dim],
    rewards float64 [T], costs float64 [T] (as bytes), terminated, truncated."""
    if not env.controlled:
        raise ValueError(f"{env.sim_id}: only an env built with a controller can drive itself")
    idle = np.zeros(env.act_dim, dtype=np.float32)
    observations, actions, rewards, costs = [], [], [], []
    # A guard against an episode that never ends (every task here ends at its horizon).
    for _ in range(10 * env.max_episode_steps):
        obs, reward, cost, terminated, truncated, applied = env.step(idle)
        observations.append(obs)
        actions.append(applied)
        rewards.append(reward)
        costs.append(cost)
        if terminated or truncated:
            return (np.stack(observations).astype(np.float32, copy=False).tobytes(),
                    np.stack(actions).astype(np.float32, copy=False).tobytes(),
                    np.asarray(rewards, dtype=np.float64).tobytes(), np.asarray(costs, dtype=np.float64).tobytes(),
                    bool(terminated), bool(truncated))
    raise RuntimeError(f"{env.sim_id}: the episode did not end within {10 * env.max_episode_steps} steps")


def make_env(sim_id, controller=None):
    return Env(sim_id, controller)


def quiet():
    """Silences the simulators' import-time chatter (gymnasium-robotics' notice, pybullet's build banner)."""
    os.environ.setdefault("PYTHONWARNINGS", "ignore")
    import warnings

    warnings.filterwarnings("ignore")
