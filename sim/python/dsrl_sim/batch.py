"""K environments of one task stepped together, with inputs and outputs as raw bytes (little-endian, C order):

    batch = Batch("SafetyBallRun-v0", seeds=[0, 1, 2], auto_reset=False)
    obs = batch.reset([0, 1, 2], [0, 1, 2])             # float32 [n, obs_dim]
    obs = batch.reset([0], [5], {"idm": {...}})         # MetaDrive, opened with a controller: switch env 0's driver
    obs, rewards, costs, terminated, truncated, final_obs, applied = batch.step([0, 1, 2], actions)
    # float32 [n, obs_dim], float64 [n], float64 [n], uint8 [n], uint8 [n], float32 [n, obs_dim] or b"",
    # float32 [n, act_dim] (the actions the simulators applied: clipped, or a controller's)
    episodes = batch.drive([0, 1])                      # opened with a controller: play the rest of each episode
    # [(observations, applied actions, rewards, costs, terminated, truncated)], see tasks.drive
    frames = batch.frames([0], 160, 160)                # uint8 [n, 160, 160, 3]: the envs drawn as they are now

Bullet-Safety-Gym and Safety-Gymnasium envs live in this process. MetaDrive allows one engine per process, so each
MetaDrive env lives in its own process (multiprocessing, spawn start method) and a batch steps them in parallel.

With auto_reset, an env that finishes is reset in the same step: its row of `obs` is the reset observation and its
row of `final_obs` the last observation of the finished episode. The k-th automatic reset of env i uses seed
`seeds[i] + k * K` (K = number of envs), so all episodes of a batch have distinct seeds.
"""
import multiprocessing
import os
import time

import numpy as np

from . import tasks


def _host(conn, sim_id, controller):
    """A MetaDrive env in its own process, driven over a pipe; it exits quietly when its parent goes away."""
    try:
        env = tasks.make_env(sim_id, controller)
        conn.send((env.obs_dim, env.act_dim, env.low, env.high, env.max_episode_steps))
        while True:
            command, argument = conn.recv()
            if command == "reset":
                seed, switch = argument
                conn.send(env.reset(seed, switch))
            elif command == "step":
                conn.send(env.step(argument))
            elif command == "drive":
                conn.send(tasks.drive(env))
            elif command == "frame":
                conn.send(env.frame(*argument))
            else:
                env.close()
                conn.send(None)
                return
    except (EOFError, OSError):  # the parent is gone: nothing left to serve
        return


class _Remote:
    """The parent side of a `_host` process, with the `Env` interface split into send/receive halves."""

    def __init__(self, sim_id, controller, context):
        self.conn, child = context.Pipe()
        self.process = context.Process(target=_host, args=(child, sim_id, controller), daemon=True)
        self.process.start()
        child.close()
        self.obs_dim, self.act_dim, self.low, self.high, self.max_episode_steps = self.conn.recv()

    def send(self, command, argument=None):
        self.conn.send((command, argument))

    def receive(self):
        return self.conn.recv()

    def close(self):
        try:
            self.send("close")
            self.receive()
        except (EOFError, OSError, BrokenPipeError):
            pass
        self.process.join(timeout=10)
        if self.process.is_alive():
            self.process.kill()


class Batch:
    def __init__(self, sim_id, seeds, auto_reset, controller=None):
        # CPU time this thread spends building the envs (a MetaDrive env's own process is not counted): the worker
        # logs it with the session, so a benchmark can tell building from stepping.
        started = time.thread_time()
        self.sim_id = sim_id
        self.seeds = [int(s) for s in seeds]
        self.auto_reset = bool(auto_reset)
        self.resets = [0] * len(self.seeds)
        self.remote = tasks.family(sim_id) == tasks.METADRIVE
        if self.remote:
            context = multiprocessing.get_context("spawn")
            python = os.environ.get("DSRL_SIM_PYTHON")
            if python:  # embedded: sys.executable is the worker binary, not a Python
                context.set_executable(python)
            self.envs = [_Remote(sim_id, controller, context) for _ in self.seeds]
        else:
            self.envs = [tasks.make_env(sim_id, controller) for _ in self.seeds]
        first = self.envs[0]
        self.obs_dim, self.act_dim = first.obs_dim, first.act_dim
        self.low, self.high, self.max_episode_steps = first.low, first.high, first.max_episode_steps
        self.build_cpu_seconds = time.thread_time() - started

    def _reset_many(self, indices, seeds, switch=None):
        if self.remote:
            for i, s in zip(indices, seeds):
                self.envs[i].send("reset", (s, switch))
            return [self.envs[i].receive() for i in indices]
        return [self.envs[i].reset(s, switch) for i, s in zip(indices, seeds)]

    def reset(self, indices, seeds, switch=None):
        """Resets the envs at `indices`; `switch` (a controller) changes their driver from this episode on."""
        rows = self._reset_many(list(indices), list(seeds), switch)
        return np.stack(rows).astype(np.float32, copy=False).tobytes()

    def step(self, indices, actions):
        indices = list(indices)
        actions = np.frombuffer(actions, dtype=np.float32).reshape(len(indices), self.act_dim)
        if self.remote:
            for i, a in zip(indices, actions):
                self.envs[i].send("step", a)
            results = [self.envs[i].receive() for i in indices]
        else:
            results = [self.envs[i].step(a) for i, a in zip(indices, actions)]
        obs = np.stack([r[0] for r in results]).astype(np.float32, copy=False)
        rewards = np.array([r[1] for r in results], dtype=np.float64)
        costs = np.array([r[2] for r in results], dtype=np.float64)
        terminated = np.array([r[3] for r in results], dtype=np.uint8)
        truncated = np.array([r[4] for r in results], dtype=np.uint8)
        applied = np.stack([r[5] for r in results]).astype(np.float32, copy=False)
        final = b""
        if self.auto_reset:
            finished = [k for k in range(len(indices)) if terminated[k] or truncated[k]]
            final_obs = np.zeros_like(obs)
            if finished:
                envs = [indices[k] for k in finished]
                seeds = []
                for i in envs:
                    self.resets[i] += 1
                    seeds.append(self.seeds[i] + self.resets[i] * len(self.seeds))
                fresh = self._reset_many(envs, seeds)
                for k, row in zip(finished, fresh):
                    final_obs[k] = obs[k]
                    obs[k] = row
            final = final_obs.tobytes()
        return (obs.tobytes(), rewards.tobytes(), costs.tobytes(), terminated.tobytes(), truncated.tobytes(), final,
                applied.tobytes())

    def drive(self, indices):
        """The rest of each named env's episode, its controller driving; MetaDrive's processes play in parallel."""
        indices = list(indices)
        if self.remote:
            for i in indices:
                self.envs[i].send("drive")
            return [self.envs[i].receive() for i in indices]
        return [tasks.drive(self.envs[i]) for i in indices]

    def frames(self, indices, width, height):
        """RGB images of the named envs as they are now: uint8 [n, height, width, 3] (see `tasks.Env.frame`)."""
        indices = list(indices)
        if self.remote:
            for i in indices:
                self.envs[i].send("frame", (width, height))
            images = [self.envs[i].receive() for i in indices]
        else:
            images = [self.envs[i].frame(width, height) for i in indices]
        return np.stack(images).astype(np.uint8, copy=False).tobytes()

    def close(self):
        for env in self.envs:
            env.close()
        self.envs = []
