"""DSRL's nine SafeMetaDrive tasks, ported to MetaDrive 0.4.3.

DSRL defines them (dsrl/offline_metadrive/gym_envs.py) for the MetaDrive 0.2/0.3 API; 0.4.3 renamed
`environment_num` to `num_scenarios`, takes `reset(seed=...)` and returns five values from `step`. Everything else is
as DSRL has it: the extra default config, the cost terms added to MetaDrive's own cost (out of road / crash), and
termination on arrival, crash or leaving the road, truncation at the 1000-step horizon.

Seeds: DSRL's configs hold one scenario (the map, `start_seed`), and `random_traffic=True` keeps MetaDrive from
reseeding the traffic per scenario, so DSRL's episodes were seeded by nothing. Here the episode seed seeds the traffic
generator at every reset: the map stays DSRL's, the traffic varies by seed and is reproducible.

Maps: DSRL evaluates on the task's one map, but collected its datasets on 10 (`run_collect.sh` passes
`environment_num=10` to `sample_data.py`: maps `start_seed` .. `start_seed + 9`, one drawn per reset). A session
opened with the IDM driver and `maps = n` draws each episode's map from its seed among the first n.

The out-ramp fix: MetaDrive 0.4.3 builds the out-ramp block (`R`, in the hard maps' "TRO" only) wrongly once the
road has turned, so its lanes cross the carriageway; see `_restore_out_ramp`.
"""
import numpy as np
from metadrive.base_class.randomizable import Randomizable
from metadrive.component.lane.extension_lane import ExtendingLane, ExtensionDirection
from metadrive.component.pg_space import BoxSpace, ConstantSpace, Parameter, ParameterSpace
from metadrive.component.pgblock.ramp import OutRampOnStraight
from metadrive.component.vehicle.PID_controller import PIDController
from metadrive.constants import PGLineType
from metadrive.envs import SafeMetaDriveEnv
from metadrive.manager.traffic_manager import TrafficMode
from metadrive.policy.idm_policy import IDMPolicy


def _restore_out_ramp():
    """Gives MetaDrive 0.4.3's out-ramp block the geometry of DSRL's fork (metadrive_clean, MetaDrive 0.2.6).

    0.4.3 builds the taper where the exit lane opens with `create_extension`, which ends it at `start + [length, 0]`:
    along world x, whatever the road's heading. On a road that has turned (the hard maps turn at their T-junction
    on 8 of seeds 200-209, map 200 among them), the exit lane and its ramp then run diagonally across the three main
    lanes with solid lines, and an IDM car following its lane touches one and leaves the road at 62% of the route:
    every hard-map episode ended there, at reward <= 197 against the paper's 487. The fork runs the taper along the
    lane. 0.4.3 also samples a new `extension_length` (20-40 m, drawn equal to `length`) where the fork's taper is one
    lane width, which lengthens every route by 26-36 m; it is pinned to the lane width (3.5 m in DSRL's maps).
    Checked against the fork on seeds 200-209: the same route lengths, and map 203 (a 444 m route) completes with
    reward 486.8 where the fork gives 486.3-486.6. The easy ("SCS") and medium ("XST") maps have no out-ramp."""

    def taper_along_the_lane(self, att_lane, length):
        start = att_lane.position(0, self.lane_width)
        end = att_lane.position(length, self.lane_width)
        return ExtendingLane(ExtensionDirection.EXTEND, start, end, self.lane_width,
                             [PGLineType.NONE, PGLineType.CONTINUOUS])

    OutRampOnStraight._get_merge_part = taper_along_the_lane
    OutRampOnStraight.PARAMETER_SPACE = ParameterSpace(
        {Parameter.length: BoxSpace(min=20, max=40), Parameter.extension_length: ConstantSpace(3.5)})


# Before any map is built: MetaDrive keeps the maps it has built for the life of the process.
_restore_out_ramp()

class IDMCustomSpeed(IDMPolicy):
    """The noisy IDM driver of DSRL's MetaDrive data collection (metadrive_clean `IDMPolicy_CustomSpeed`, spec §6.5):
    target speed and acceleration factor from the env config, lane changes off, DSRL's PID gains, and uniform
    noise on steering (+-0.1) and acceleration (+0..0.2) drawn from `np.random`, which the env seeds at every reset
    (this process hosts one env, so the global generator is the env's own)."""

    def __init__(self, control_object, random_seed):
        super().__init__(control_object, random_seed)
        config = self.engine.global_config
        self.NORMAL_SPEED = config.get("idm_target_speed", 30)
        self.DISTANCE_WANTED = 10.0 - config.get("idm_target_speed", 30) / 6.0
        self.target_speed = config.get("idm_target_speed", 30)
        self.ACC_FACTOR = config.get("idm_acc_factor", 1.0)
        self.DEACC_FACTOR = config.get("idm_deacc_factor", 5.0)
        self.LANE_CHANGE_FREQ = 1000
        self.enable_lane_change = False
        self.heading_pid = PIDController(self.KP_HEADING, 0.01, 3.5)
        self.lateral_pid = PIDController(self.KP_LATERAL, 0.002, 0.05)

    def act(self, *args, **kwargs):
        steering, acc = super().act(*args, **kwargs)
        steering += 0.2 * (np.random.rand() - 0.5)
        acc += 0.2 * np.random.rand()
        action = [float(np.clip(steering, -1.0, 1.0)), float(np.clip(acc, -1.0, 1.0))]
        self.action_info["action"] = action
        return action


ROADS = {"easy": (0, "SCS"), "medium": (100, "XST"), "hard": (200, "TRO")}
TRAFFIC = {"sparse": 0.1, "mean": 0.15, "dense": 0.2}
HORIZON = 1000


class SafeMetaDrive(SafeMetaDriveEnv):
    def default_config(self):
        config = super().default_config()
        config.update(
            {
                "idm_target_speed": 30,
                "idm_acc_factor": 1.0,
                "idm_deacc_factor": 5.0,
                "crash_vehicle_penalty": 0.0,
                "random_traffic": True,
                "traffic_mode": TrafficMode.Hybrid,
            },
            allow_add_new_key=True,
        )
        return config

    def __init__(self, config):
        self._episode_seed = 0
        super().__init__(config)

    def set_controller(self, controller):
        """Switches the IDM driver's settings from the next reset on: MetaDrive builds the agent's policy anew at
        every reset from the env config (checked: an episode after a switch equals one in a fresh env at the new
        settings), so a sweep can reuse one env for many settings instead of paying ~4 s to build each. The maps
        stay those the env was made with (the worker refuses a switch that names others)."""
        idm = controller["idm"]
        if int(idm.get("maps", 1)) != self.config["num_scenarios"]:
            raise ValueError(f"a switch cannot change the env's {self.config['num_scenarios']} maps")
        self.config["idm_target_speed"] = float(idm["target_speed"])
        self.config["idm_acc_factor"] = float(idm["acc_factor"])

    def _reset_global_seed(self, force_seed=None):
        super()._reset_global_seed(force_seed)
        # The traffic manager ignores seeding while random_traffic is on; seed its generator directly.
        Randomizable.seed(self.engine.traffic_manager, self._episode_seed % (2**32))

    def reset(self, seed=None, options=None):
        self._episode_seed = 0 if seed is None else int(seed)
        # The IDM driver's noise (when it drives) comes from np.random: seed it per episode too.
        np.random.seed(self._episode_seed % (2**32))
        # The map, from a generator of its own so that the driver's noise stays what it is with one map.
        maps = self.config["num_scenarios"]
        k = 0 if maps == 1 else int(np.random.default_rng(self._episode_seed).integers(maps))
        obs, _ = super().reset(seed=self.config["start_seed"] + k)
        return obs, {}

    def step(self, actions):
        o, r, _, _, i = super().step(actions)
        # DSRL's fork reports speed in km/h; MetaDrive 0.4.3's info["velocity"] is m/s.
        i["velocity_cost"] = max(0.0, 1e-2 * (self.agent.speed_km_h - 10.0))
        i["cost"] += i["velocity_cost"]
        i["proximity_cost"] = 1e-2 * max(0.0, 0.1 - float(np.min(o[-240:]))) ** 2
        i["cost"] += i["proximity_cost"]
        terminated = bool(i["arrive_dest"] or i["crash"] or i["out_of_road"])
        truncated = bool(i["max_step"])
        return o, r, terminated, truncated, i


def make(sim_id, controller=None):
    """`SafeMetaDrive-{easy,medium,hard}{sparse,mean,dense}-v0`. `controller={"idm": {"target_speed": v,
    "acc_factor": a, "maps": n}}` lets the noisy IDM driver steer (the actions passed to `step` are then ignored;
    the env reports the applied action in `info["raw_action"]`) on the task's first n maps (default 1: its own)."""
    extra = {}
    maps = 1
    if controller:
        idm = controller["idm"]
        maps = max(1, int(idm.get("maps", 1)))
        extra = {"agent_policy": IDMCustomSpeed, "idm_target_speed": float(idm["target_speed"]),
                 "idm_acc_factor": float(idm["acc_factor"])}
    name = sim_id[len("SafeMetaDrive-"):-len("-v0")]
    for road, (start_seed, blocks) in ROADS.items():
        if name.startswith(road) and name[len(road):] in TRAFFIC:
            return SafeMetaDrive(
                {
                    "start_seed": start_seed,
                    "traffic_density": TRAFFIC[name[len(road):]],
                    "map": 3,
                    "map_config": {"type": "block_sequence", "config": blocks},
                    "accident_prob": 0.0,
                    "num_scenarios": maps,
                    "horizon": HORIZON,
                    "use_render": False,
                    "log_level": 50,
                    **extra,
                }
            )
    raise KeyError(sim_id)
