"""Faster versions of the pinned simulators' own Python, applied when the first env of a family is made.

Each replaces one library function with one that computes the same numbers in fewer Python and NumPy calls. None
changes an observation, reward, cost or episode end: `verify` plays a task's episodes twice side by side, once
with the library's functions and once with these, and compares every value bit for bit (sim/tests/it/speedups.rs
runs it, and checks that it catches a speed-up that is off in the last bit). Rendered images are the one output a
speed-up may change (the skybox's). `bench/sim_speedups.py` measures what each one saves. They replace the library's
classes' methods for the whole process, so a Safety-Gymnasium env made directly in the same process (beside the
Python package's envs) steps with them too, to the same numbers.

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
4. Contact costs (vases, pillars, gremlins, buttons). After every step each of these walks the step's contacts (a
   few dozen with the vases of a level-2 task) and looks both geoms' names up through MuJoCo's named accessor to
   count the contacts between the agent and one of its geoms. The fast `cal_cost` counts the same contacts from the
   contact arrays and a per-model list of geom names, then adds the cost once per counted contact, as the loop does
   (the same additions in the same order). The vases' displacement and velocity costs stay the library's own.
5. The pseudo-lidar (every observation: one lidar per observed kind of object, over each object's position).
   The library reads the agent's position and rotation from MuJoCo once per object; they cannot change within an
   observation, so the fast one reads them once per lidar and does the rest with the library's own operations.

Bullet-Safety-Gym (applied when the first Bullet env is made; its physics, pybullet's `stepSimulation`, is a third
of a BallCircle step, its own Python the rest):

6. The client's function lookup. pybullet_utils' `BulletClient` finds every pybullet function through
   `__getattr__` at each call: a module lookup, `inspect.isbuiltin` and a new `functools.partial` binding the client
   id, a dozen times a step. The fast `__getattr__` does the same once per name and keeps the partial on the client
   (the same function with the same client id), except `disconnect`, which changes the id and drops the kept ones.
7. A body's and a link's `get_state` (nine times a BallCircle step): `np.concatenate` over four tuples of floats
   becomes one `np.array` over their concatenation, the same twelve float64 values.
8. An agent's action clip: `np.clip` becomes `np.minimum(np.maximum(...))`, the same values for the finite actions
   the library asserts (`np.clip`'s own checks cost more than the two ufuncs).
"""
import functools
import math

import numpy as np

_applied = set()
# The library's functions the speed-ups replace, by "Class.method": (owner, method name, the library's function). A
# speed-up that still calls its library function and `verify` read them here.
_replaced = {}


def _replace(owner, name, fast):
    _replaced[f"{owner.__name__}.{name}"] = (owner, name, getattr(owner, name))
    setattr(owner, name, fast)


def _library(key):
    """The library's own function for "Class.method"."""
    return _replaced[key][2]


def apply_safety_gymnasium():
    """Installs the Safety-Gymnasium speed-ups (once per process)."""
    if "safety-gymnasium" in _applied:
        return
    import safety_gymnasium.world as world
    from safety_gymnasium.assets.free_geoms import vases
    from safety_gymnasium.assets.geoms import buttons, pillars
    from safety_gymnasium.assets.mocaps import gremlins
    from safety_gymnasium.bases import base_task
    from safety_gymnasium.utils import random_generator

    load = world.yaml.load

    def gradient_skybox(stream, Loader=None):
        data = load(stream, Loader=Loader)
        if isinstance(data, dict) and "skybox" in data.get("textures", {}):
            data["textures"]["skybox"] = {"@type": "skybox", "@builtin": "gradient", "@rgb1": "0.4 0.6 0.8",
                                          "@rgb2": "0 0 0", "@width": "32", "@height": "32"}
        return data

    world.yaml.load = gradient_skybox
    # The lambdas look the fast function up at each call, so a test can swap in a broken version and see `verify`
    # catch it (the contact costs' own helper, `_agent_contacts`, is looked up the same way).
    _replace(gremlins.Gremlins, "move", lambda self: _fast_gremlins_move(self))
    _replace(random_generator.RandomGenerator, "sample_layout", lambda self: _fast_sample_layout(self))
    _replace(base_task.BaseTask, "_obs_lidar_pseudo", lambda self, positions: _fast_lidar_pseudo(self, positions))
    for owner, fast in ((vases.Vases, _fast_vases_cost), (pillars.Pillars, _fast_pillars_cost),
                        (gremlins.Gremlins, _fast_gremlins_cost), (buttons.Buttons, _fast_buttons_cost)):
        _replace(owner, "cal_cost", fast)
    _applied.add("safety-gymnasium")


def apply_bullet_safety_gym():
    """Installs the Bullet-Safety-Gym speed-ups (once per process)."""
    if "bullet-safety-gym" in _applied:
        return
    from bullet_safety_gym.envs import bases
    from pybullet_utils import bullet_client

    _replace(bullet_client.BulletClient, "__getattr__", lambda self, name: _fast_client_getattr(self, name))
    _replace(bases.Body, "get_state", lambda self: _fast_body_state(self))
    _replace(bases.Link, "get_state", lambda self: _fast_link_state(self))
    _replace(bases.Agent, "apply_action", lambda self, action: _fast_agent_clip(self, action))
    _applied.add("bullet-safety-gym")


def _fast_client_getattr(self, name):
    """`BulletClient.__getattr__`, keeping what it finds: Python calls `__getattr__` only for a name the client's
    own attributes lack, so a kept partial answers every later lookup directly."""
    attribute = _library("BulletClient.__getattr__")(self, name)
    if name == "disconnect":
        for kept in [k for k, v in vars(self).items() if isinstance(v, functools.partial)]:
            del self.__dict__[kept]
    elif isinstance(attribute, functools.partial):
        self.__dict__[name] = attribute
    return attribute


def _fast_body_state(self):
    """`Body.get_state`: base position, base velocity, Euler angles, angular velocity."""
    import pybullet

    xyz, abcd = self.bc.getBasePositionAndOrientation(self.body_id)
    xyz_dot, rpy_dot = self.bc.getBaseVelocity(self.body_id)
    return np.array(xyz + xyz_dot + pybullet.getEulerFromQuaternion(abcd) + rpy_dot)


def _fast_link_state(self):
    """`Link.get_state`: the base's state for link -1, the link's world state otherwise."""
    import pybullet

    if self.index == -1:
        xyz, abcd = self.bc.getBasePositionAndOrientation(self.body_id)
        xyz_dot, rpy_dot = self.bc.getBaseVelocity(self.body_id)
    else:
        xyz, abcd, _, _, _, _, xyz_dot, rpy_dot = self.bc.getLinkState(self.body_id, self.index,
                                                                      computeLinkVelocity=1)
    return np.array(xyz + xyz_dot + pybullet.getEulerFromQuaternion(abcd) + rpy_dot)


def _fast_agent_clip(self, action):
    """`Agent.apply_action` (the base class's: check, then clip into [-1, 1])."""
    assert np.isfinite(action).all()
    return np.minimum(np.maximum(action, -1.0), 1.0)


def _fast_gremlins_move(self):
    """`Gremlins.move` with the same arithmetic: target = [sin t, cos t] * travel, then (target, size) for every
    gremlin's mocap position."""
    engine = self.engine
    phase = float(engine.data.time)
    target = np.array([np.sin(phase), np.cos(phase)]) * self.travel
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


def _fast_lidar_pseudo(self, positions):
    """`BaseTask._obs_lidar_pseudo`: per position, the egocentric XY vector (`_ego_xy`'s operations), its distance
    and angle, the bin it falls in and, with aliasing, the two bins beside it, each keeping its largest reading."""
    conf = self.lidar_conf
    num_bins = conf.num_bins
    obs = np.zeros(num_bins)
    agent_3vec = self.agent.pos
    agent_mat = self.agent.mat
    bin_size = (np.pi * 2) / num_bins
    for pos in np.array(positions, ndmin=2):
        pos = np.asarray(pos)
        if pos.shape == (3,):
            pos = pos[:2]
        assert pos.shape == (2,), f"Bad pos {pos}"
        ego = np.matmul(np.concatenate([pos, [0]]) - agent_3vec, agent_mat)[:2]
        z = complex(*ego)
        dist = np.abs(z)
        angle = np.angle(z) % (np.pi * 2)
        bin = int(angle / bin_size)  # noqa: A001  (the library's name)
        bin_angle = bin_size * bin
        if conf.max_dist is None:
            sensor = np.exp(-conf.exp_gain * dist)
        else:
            sensor = max(0, conf.max_dist - dist) / conf.max_dist
        obs[bin] = max(obs[bin], sensor)
        if conf.alias:
            alias = (angle - bin_angle) / bin_size
            assert 0 <= alias <= 1, f"bad alias {alias}, dist {dist}, angle {angle}, bin {bin}"
            bin_plus = (bin + 1) % num_bins
            bin_minus = (bin - 1) % num_bins
            obs[bin_plus] = max(obs[bin_plus], alias * sensor)
            obs[bin_minus] = max(obs[bin_minus], (1 - alias) * sensor)
    return obs


def _geom_names(obj):
    """Each geom's name in the object's current MuJoCo model (cached per model: it is rebuilt at each reset)."""
    model = obj.engine.model
    cached = getattr(obj, "_dsrl_geom_names", None)
    if cached is None or cached[0] is not model:
        cached = (model, [model.geom(i).name for i in range(model.ngeom)])
        obj._dsrl_geom_names = cached
    return cached[1]


def _agent_contacts(obj, prefix, exclude=None):
    """How many of the current contacts the library's loops count: one geom's name starts with `prefix`, one geom
    is the agent's, and neither is named `exclude`."""
    data = obj.engine.data
    ncon = data.ncon
    if not ncon:
        return 0
    names = _geom_names(obj)
    agent = obj.agent.body_info.geom_names
    contacts = data.contact
    counted = 0
    for a, b in zip(contacts.geom1[:ncon].tolist(), contacts.geom2[:ncon].tolist()):
        first, second = names[a], names[b]
        if ((first.startswith(prefix) or second.startswith(prefix)) and (first in agent or second in agent)
                and first != exclude and second != exclude):
            counted += 1
    return counted


def _added(cost, times):
    """0 plus `cost`, `times` times over: the loop's float additions, in its order."""
    total = 0
    for _ in range(times):
        total += cost
    return total


def _fast_pillars_cost(self):
    if not self.is_constrained:
        return {}
    return {"cost_pillars": _added(self.cost, _agent_contacts(self, "pillar"))}


def _fast_gremlins_cost(self):
    if not self.is_constrained:
        return {}
    return {"cost_gremlins": _added(self.contact_cost, _agent_contacts(self, "gremlin"))}


def _fast_buttons_cost(self):
    assert self.goal_button is not None, "Please make sure this method can get information about goal button."
    if not self.is_constrained or self.timer != 0:
        return {}
    touched = _agent_contacts(self, "button", exclude=f"button{self.goal_button}")
    return {"cost_buttons": _added(self.cost, touched)}


def _fast_vases_cost(self):
    """The library's own `cal_cost` with its contact loop switched off (a zero contact cost skips it, leaving the
    key at 0 in its place among the keys), then the contact cost counted here."""
    contact_cost = self.contact_cost
    self.contact_cost = 0
    try:
        cost = _library("Vases.cal_cost")(self)
    finally:
        self.contact_cost = contact_cost
    if contact_cost and "cost_vases_contact" in cost:
        cost["cost_vases_contact"] = _added(contact_cost, _agent_contacts(self, "vase"))
    return cost


class LibraryFunctions:
    """Within `with`: the library's own functions in place of the speed-ups."""

    def __enter__(self):
        self.fast = [(owner, name, getattr(owner, name)) for owner, name, _ in _replaced.values()]
        for owner, name, original in _replaced.values():
            setattr(owner, name, original)

    def __exit__(self, *exc):
        for owner, name, fast in self.fast:
            setattr(owner, name, fast)
        return False


def verify(sim_id, steps, seed=0, episode_steps=None):
    """Plays `steps` steps of `sim_id` (episodes from seeds `seed`, `seed + 1`, ...; each episode cut after
    `episode_steps` steps when given, so that a short check crosses many resets) on two envs, stepping one with the
    library's functions and the other with the speed-ups, and raises AssertionError at the first value that differs
    in any bit: outputs, the layout drawn at each reset, the physics state after each step (MuJoCo's data, or every
    pybullet body's), and the replaced readings (contact costs, lidar, Bullet's `get_state`s) against the
    library's on the sped-up env's state. Each episode heads one
    way (an action drawn uniformly at its start, held with Gaussian noise of 0.3, clipped; a generator seeded by
    `seed`): uniform noise alone keeps the agent near its start, where the obstacles' contact costs go unchecked.
    -> the number of steps, episodes and steps with a cost compared."""
    from . import tasks

    bullet = tasks.family(sim_id) == tasks.BULLET
    fast = tasks.make_env(sim_id)  # installs the speed-ups
    with LibraryFunctions():
        library = tasks.make_env(sim_id)
    actions = np.random.default_rng(seed)
    episode, compared, episodes, costly = seed, 0, 0, 0
    while compared < steps:
        with LibraryFunctions():
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
        heading = actions.uniform(-1.0, 1.0, fast.act_dim)
        while not done and compared < steps and played != episode_steps:
            action = np.clip(heading + actions.normal(0.0, 0.3, fast.act_dim), -1.0, 1.0)
            with LibraryFunctions():
                expected = library.step(action)
            got = fast.step(action)
            for what, a, b in zip(("observation", "reward", "cost", "terminated", "truncated", "action"), expected,
                                  got):
                _same(sim_id, f"episode {episode} step {compared} {what}", a, b)
            # The whole physics state too: a difference can stay out of the observations for many steps (the
            # lidar bins positions) and still change a later episode.
            if bullet:
                with LibraryFunctions():
                    expected = _bullet_physics(library)
                _same(sim_id, f"episode {episode} step {compared} physics", expected, _bullet_physics(fast))
                _same_bullet_readings(sim_id, f"episode {episode} step {compared}", fast)
            else:
                for what in _STATE:
                    _same(sim_id, f"episode {episode} step {compared} {what}", _physics(library, what),
                          _physics(fast, what))
                _same_readings(sim_id, f"episode {episode} step {compared}", fast)
            compared += 1
            played += 1
            costly += got[2] > 0
            done = got[3] or got[4]
        episode += 1
    fast.close()
    library.close()
    return compared, episodes, int(costly)


# What MuJoCo carries from one substep to the next: positions, velocities, the mocap targets, controls, actuator
# states, the simulated time and the solver's warm start.
_STATE = ("qpos", "qvel", "mocap_pos", "mocap_quat", "ctrl", "act", "time", "qacc_warmstart")


def _same_readings(sim_id, where, env):
    """The replaced readings against the library's, on the env's state as it is: each obstacle's contact cost (the
    count itself, which the tasks' indicator costs hide) and lidar (in float64, before the observation's float32)."""
    task = getattr(env._env.unwrapped, "task", None)
    for obstacle in getattr(task, "_obstacles", []):
        replaced = _replaced.get(type(obstacle).__name__ + ".cal_cost")
        if replaced is not None:
            expected, got = replaced[2](obstacle), type(obstacle).cal_cost(obstacle)
            if list(expected.items()) != list(got.items()):
                raise AssertionError(f"{sim_id}: {where}: {type(obstacle).__name__} cost: the speed-ups give {got}, "
                                     f"the library {expected}")
        if getattr(obstacle, "is_lidar_observed", False) and task.lidar_conf.type == "pseudo":
            positions = obstacle.pos
            _same(sim_id, f"{where} {obstacle.name} lidar", _library("BaseTask._obs_lidar_pseudo")(task, positions),
                  task._obs_lidar_pseudo(positions))


def _bullet_physics(env):
    """pybullet's state of every body: base position, orientation and velocities, and each joint's position,
    velocity and applied torque."""
    bc = env._env.unwrapped.bc
    values = []
    for i in range(bc.getNumBodies()):
        body = bc.getBodyUniqueId(i)
        for part in bc.getBasePositionAndOrientation(body) + bc.getBaseVelocity(body):
            values.extend(part)
        for joint in range(bc.getNumJoints(body)):
            position, velocity, _, torque = bc.getJointState(body, joint)
            values.extend((position, velocity, torque))
    return np.array(values)


def _same_bullet_readings(sim_id, where, env):
    """The replaced `get_state`s against the library's on the env's state as it is: the agent's body and its links."""
    agent = env._env.unwrapped.agent
    _same(sim_id, f"{where} agent state", _library("Body.get_state")(agent), agent.get_state())
    for link in agent.link_list:
        _same(sim_id, f"{where} link {link.index} state", _library("Link.get_state")(link), link.get_state())


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
