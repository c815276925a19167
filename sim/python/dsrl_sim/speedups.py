"""Faster versions of the pinned simulators' own Python, applied when the first Safety-Gymnasium env is made.

Each replaces one library function with one that computes the same numbers in fewer Python and NumPy calls. None
changes an observation, reward, cost or episode end: `verify` plays a task's episodes twice side by side, once
with the library's functions and once with these, and compares every value bit for bit (sim/tests/it/speedups.rs
runs it, and checks that it catches a speed-up that is off in the last bit). Rendered images are the one output a
speed-up may change (the skybox's). `bench/sim_speedups.py` measures what each one saves.

1. The skybox. Safety-Gymnasium rebuilds its MuJoCo model at every reset and decodes 24 MB of skybox PNGs each
   time; a builtin gradient skybox cuts a reset from ~1.4 s to ~15 ms. The skybox is only drawn, never simulated.
2. Gremlins (the moving obstacles of the Button tasks). `Gremlins.move` runs before every physics substep, ten a
   step, and for each gremlin builds the same circle target with `np.r_` (whose type promotion alone costs more
   than the MuJoCo substep) and looks its mocap body up by name. The fast `move` computes the target once, with the
   same NumPy operations, and writes it into every gremlin's mocap row by an index cached per MuJoCo model (the
   model is rebuilt at each reset, and the cache with it).
3. The layout. Every reset draws the objects' places by rejection sampling, and each candidate is tested against
   every object placed so far with `np.sqrt(np.sum(np.square(xy - other)))`: three NumPy calls on 2-vectors, some
   hundred thousand of them per Button reset. The fast `sample_layout` draws the same candidates in the same order
   (`draw_placement`, the library's own) and tests them with the same IEEE operations on Python floats: an
   element-wise difference, squares, the sum of two (NumPy adds a 2-vector's elements in order) and a correctly
   rounded square root, against the threshold summed in the library's order.
"""
import math

import numpy as np

_applied = False
# The library's functions the speed-ups replace, for `verify`: (owner, attribute name, the library's function).
_replaced = []


def apply_safety_gymnasium():
    """Installs the Safety-Gymnasium speed-ups (once per process)."""
    global _applied
    if _applied:
        return
    import safety_gymnasium.world as world
    from safety_gymnasium.assets.mocaps import gremlins
    from safety_gymnasium.utils import random_generator

    load = world.yaml.load

    def gradient_skybox(stream, Loader=None):
        data = load(stream, Loader=Loader)
        if isinstance(data, dict) and "skybox" in data.get("textures", {}):
            data["textures"]["skybox"] = {"@type": "skybox", "@builtin": "gradient", "@rgb1": "0.4 0.6 0.8",
                                          "@rgb2": "0 0 0", "@width": "32", "@height": "32"}
        return data

    world.yaml.load = gradient_skybox
    _replaced.append((gremlins.Gremlins, "move", gremlins.Gremlins.move))
    # Looked up at each call, so a test can swap in a broken version and see `verify` catch it.
    gremlins.Gremlins.move = lambda self: _fast_gremlins_move(self)
    _replaced.append((random_generator.RandomGenerator, "sample_layout",
                      random_generator.RandomGenerator.sample_layout))
    random_generator.RandomGenerator.sample_layout = lambda self: _fast_sample_layout(self)
    _applied = True


def _fast_gremlins_move(self):
    """`Gremlins.move` with the same arithmetic: target = [sin t, cos t] * travel, then (target, size) for every
    gremlin's mocap position."""
    engine = self.engine
    target = np.array([np.sin(float(engine.data.time)), np.cos(float(engine.data.time))]) * self.travel
    model = engine.model
    cached = getattr(self, "_dsrl_mocap_rows", None)
    if cached is None or cached[0] is not model:
        rows = [model.body_mocapid[model.body(f"gremlin{i}mocap").id] for i in range(self.num)]
        cached = (model, np.array(rows, dtype=np.intp))
        self._dsrl_mocap_rows = cached
    rows = cached[1]
    positions = engine.data.mocap_pos
    positions[rows, 0] = target[0]
    positions[rows, 1] = target[1]
    positions[rows, 2] = self.size


def _fast_sample_layout(self):
    """`RandomGenerator.sample_layout`: each object in turn, up to 100 candidates, the first one far enough from
    every object placed before it; False (and no layout) when an object finds none."""
    margin = self.placements_margin
    layout = {}
    # Per placed object: x, y and its keepout plus the margin (the library's threshold adds them first).
    placed = []
    for name, (placements, keepout) in self.placements.items():
        for _ in range(100):
            xy = self.draw_placement(placements, keepout)
            x, y = float(xy[0]), float(xy[1])
            for other_x, other_y, reach in placed:
                dx, dy = x - other_x, y - other_y
                if math.sqrt(dx * dx + dy * dy) < reach + keepout:
                    break
            else:
                break
        else:
            return False
        layout[name] = xy
        placed.append((x, y, self.placements[name][1] + margin))
    self.layout = layout
    return True


class _LibraryFunctions:
    """Within `with`: the library's own functions in place of the speed-ups."""

    def __enter__(self):
        self.fast = [(owner, name, getattr(owner, name)) for owner, name, _ in _replaced]
        for owner, name, original in _replaced:
            setattr(owner, name, original)

    def __exit__(self, *exc):
        for owner, name, fast in self.fast:
            setattr(owner, name, fast)
        return False


def verify(sim_id, steps, seed=0, episode_steps=None):
    """Plays `steps` steps of `sim_id` (episodes from seeds `seed`, `seed + 1`, ...; uniform random actions from a
    generator seeded by `seed`; each episode cut after `episode_steps` steps when given, so that a short check
    crosses many resets) on two envs, stepping one with the library's functions and the other with the speed-ups,
    and raises AssertionError at the first value that differs in any bit: outputs, the layout drawn at each reset,
    the physics state after each step. -> the number of steps and episodes compared."""
    from . import tasks

    fast = tasks.make_env(sim_id)  # installs the speed-ups
    with _LibraryFunctions():
        library = tasks.make_env(sim_id)
    actions = np.random.default_rng(seed)
    episode, compared, episodes = seed, 0, 0
    while compared < steps:
        with _LibraryFunctions():
            expected = library.reset(episode)
        _same(sim_id, f"reset {episode}", expected, fast.reset(episode))
        expected_layout, layout = _layout(library), _layout(fast)
        if list(expected_layout) != list(layout):
            raise AssertionError(f"{sim_id}: reset {episode}: the layouts place {list(layout)}, not "
                                 f"{list(expected_layout)}")
        for name in layout:
            _same(sim_id, f"reset {episode} layout {name}", expected_layout[name], layout[name])
        episodes += 1
        done, played = False, 0
        while not done and compared < steps and played != episode_steps:
            action = actions.uniform(-1.0, 1.0, fast.act_dim)
            with _LibraryFunctions():
                expected = library.step(action)
            got = fast.step(action)
            for what, a, b in zip(("observation", "reward", "cost", "terminated", "truncated", "action"), expected,
                                  got):
                _same(sim_id, f"episode {episode} step {compared} {what}", a, b)
            # The whole physics state too: a difference can stay out of the observations for many steps (the
            # lidar bins positions) and still change a later episode.
            for what in _STATE:
                _same(sim_id, f"episode {episode} step {compared} {what}", _physics(library, what),
                      _physics(fast, what))
            compared += 1
            played += 1
            done = got[3] or got[4]
        episode += 1
    fast.close()
    library.close()
    return compared, episodes


# What MuJoCo carries from one substep to the next: positions, velocities, the mocap targets, controls, actuator
# states, the simulated time and the solver's warm start.
_STATE = ("qpos", "qvel", "mocap_pos", "mocap_quat", "ctrl", "act", "time", "qacc_warmstart")


def _layout(env):
    """The places the env's last reset drew (none for a task without a layout)."""
    info = getattr(getattr(env._env.unwrapped, "task", None), "world_info", None)
    return dict(getattr(info, "layout", None) or {})


def _physics(env, what):
    """One field of the env's MuJoCo data (the navigation tasks' builder holds it in its task, the velocity tasks'
    env itself)."""
    unwrapped = env._env.unwrapped
    return getattr(getattr(unwrapped, "task", unwrapped).data, what)


def _same(sim_id, where, expected, got):
    a, b = np.asarray(expected), np.asarray(got)
    if a.dtype != b.dtype or a.shape != b.shape or a.tobytes() != b.tobytes():
        raise AssertionError(f"{sim_id}: {where}: the speed-ups give {got!r}, the library {expected!r}")
