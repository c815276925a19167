"""DSRL's nine SafeMetaDrive tasks, ported to MetaDrive 0.4.3.

DSRL defines them (dsrl/offline_metadrive/gym_envs.py) for the MetaDrive 0.2/0.3 API; 0.4.3 renamed
`environment_num` to `num_scenarios`, takes `reset(seed=...)` and returns five values from `step`. Everything else is
as DSRL has it: the extra default config, the cost terms added to MetaDrive's own cost (out of road / crash), and
termination on arrival, crash or leaving the road, truncation at the 1000-step horizon.

Seeds: DSRL's configs hold one scenario (the map, `start_seed`), and `random_traffic=True` keeps MetaDrive from
reseeding the traffic per scenario, so DSRL's episodes were seeded by nothing. Here the episode seed seeds the traffic
generator at every reset: the map stays DSRL's, the traffic varies by seed and is reproducible.
"""
import numpy as np
from metadrive.base_class.randomizable import Randomizable
from metadrive.envs import SafeMetaDriveEnv
from metadrive.manager.traffic_manager import TrafficMode

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

    def _reset_global_seed(self, force_seed=None):
        super()._reset_global_seed(force_seed)
        # The traffic manager ignores seeding while random_traffic is on; seed its generator directly.
        Randomizable.seed(self.engine.traffic_manager, self._episode_seed % (2**32))

    def reset(self, seed=None, options=None):
        self._episode_seed = 0 if seed is None else int(seed)
        obs, _ = super().reset(seed=self.config["start_seed"])
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


def make(sim_id):
    """`SafeMetaDrive-{easy,medium,hard}{sparse,mean,dense}-v0`."""
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
                    "num_scenarios": 1,
                    "horizon": HORIZON,
                    "use_render": False,
                    "log_level": 50,
                }
            )
    raise KeyError(sim_id)
