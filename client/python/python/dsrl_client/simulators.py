"""The real simulators behind `OfflineEnv`: the adapter the server's simulator workers host (`dsrl_sim`, installed
with `pip install ./sim/python` from the repository), so an episode here steps exactly what the leaderboard scores."""

# What each family needs, with the versions the workers pin (sim/python/requirements.txt, constraints.txt).
PACKAGES = {
    "bullet-safety-gym": "bullet-safety-gym==1.4.0 gymnasium==0.28.1",
    "safety-gymnasium": "safety-gymnasium==1.0.0 mujoco==2.3.3 gymnasium==0.28.1 (safety-gymnasium with --no-deps)",
    "metadrive": "metadrive-simulator==0.4.3",
}


class SimulatorMissing(ImportError):
    """The simulator of a task is not installed; the message names the pip packages."""


def make(simulator_env_id):
    try:
        from dsrl_sim import tasks
    except ImportError as e:
        raise SimulatorMissing(
            f"{simulator_env_id} needs the simulator adapter and its simulator: from the dsrl repository, "
            f"`pip install ./sim/python` and `pip install {_packages(simulator_env_id)}` "
            "(or use the environment `sim/setup.sh` builds, .venv-sim)") from e
    try:
        return tasks.make_env(simulator_env_id)
    except ImportError as e:
        raise SimulatorMissing(f"{simulator_env_id} needs its simulator: pip install {_packages(simulator_env_id)} "
                               f"({e})") from e


def _packages(simulator_env_id):
    if simulator_env_id.startswith("SafeMetaDrive-"):
        return PACKAGES["metadrive"]
    name = simulator_env_id[len("Safety"):].split("-")[0]
    if name in {a + t for a in ("Ant", "Ball", "Car", "Drone") for t in ("Run", "Circle")}:
        return PACKAGES["bullet-safety-gym"]
    return PACKAGES["safety-gymnasium"]
