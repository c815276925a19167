"""The Python package against a real dsrl-server process (started by tests/e2e/python_package.rs, which passes
it in the environment):

    DSRL_SERVER          the server, with the golden datasets of filters/tests/it/golden/filters.json ingested
    DSRL_DATASET_DIR     an empty cache for this run
    DSRL_TEST_VERSIONS   JSON {golden dataset name: {"task", "version"}}
    DSRL_GOLDEN          filters/tests/it/golden/filters.json: DSRL's own pre_process_data outputs (sha256 per array)
    DSRL_ADMIN_TOKEN     the server's admin token
    DSRL_TEST_UPLOAD     JSON {"task", "path", "version"}: a file not yet on the server, whose conversion takes > 1 s
    DSRL_TEST_EXPORT     an empty folder, where a policy exported from arrays is left for the Rust test to play
"""
import hashlib
import json
import os
import random

import gymnasium as gym
import numpy as np
import pytest

import dsrl_client
from dsrl_client import DsrlError

VERSIONS = json.loads(os.environ["DSRL_TEST_VERSIONS"])
GOLDEN = json.load(open(os.environ["DSRL_GOLDEN"]))
KEYS = ["observations", "next_observations", "actions", "rewards", "costs", "terminals", "timeouts"]


def digest(array):
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()


def test_load_dataset_has_dsrls_keys_dtypes_and_shapes_and_equals_the_parquet_file():
    pq = pytest.importorskip("pyarrow.parquet")
    ball = VERSIONS["ball"]
    data = dsrl_client.load_dataset(ball["task"], ball["version"], progress=False)
    info = dsrl_client.task(ball["task"])
    rows = len(data["rewards"])
    assert sorted(data) == sorted(KEYS)
    assert data["observations"].shape == (rows, info["obs_dim"]) and data["observations"].dtype == np.float32
    assert data["next_observations"].shape == (rows, info["obs_dim"])
    assert data["actions"].shape == (rows, info["act_dim"]) and data["actions"].dtype == np.float32
    for key in ["rewards", "costs"]:
        assert data[key].shape == (rows,) and data[key].dtype == np.float32
    for key in ["terminals", "timeouts"]:
        assert data[key].shape == (rows,) and data[key].dtype == np.bool_
    assert data["observations"].flags.writeable
    # The file in the shared cache, read independently with pyarrow.
    assert data.path.startswith(os.environ["DSRL_DATASET_DIR"])
    table = pq.read_table(data.path)
    for key, width in [("observations", info["obs_dim"]), ("next_observations", info["obs_dim"]),
                       ("actions", info["act_dim"])]:
        expected = table.column(key).combine_chunks().flatten().to_numpy().reshape(-1, width)
        np.testing.assert_array_equal(data[key], expected)
    for key in ["rewards", "costs", "terminals", "timeouts"]:
        np.testing.assert_array_equal(data[key], table.column(key).to_numpy(zero_copy_only=False))
    assert data.version == ball["version"] and data.task == ball["task"]


def test_a_cached_version_loads_without_any_request():
    car = VERSIONS["car"]
    first = dsrl_client.load_dataset(car["task"], car["version"], progress=False)
    # Nothing listens on port 9: any request would fail with DsrlError("unreachable").
    report = dsrl_client.fetch(car["task"], car["version"], server="http://127.0.0.1:9", progress=False)
    assert report["cache_hit"] and report["downloaded_bytes"] == 0
    again = dsrl_client.load_dataset(car["task"], car["version"], server="http://127.0.0.1:9", progress=False)
    for key in KEYS:
        np.testing.assert_array_equal(first[key], again[key])
    with pytest.raises(DsrlError) as e:
        dsrl_client.load_dataset(car["task"], "latest", server="http://127.0.0.1:9", progress=False)
    assert e.value.code == "unreachable" and e.value.status is None


def test_a_bad_filter_raises_with_the_servers_code_and_message():
    ball = VERSIONS["ball"]
    with pytest.raises(DsrlError) as e:
        dsrl_client.load_dataset(ball["task"], ball["version"], filter="noise=2", progress=False)
    assert e.value.status == 400, vars(e.value)
    assert "outliers_percent=2 is outside (0, 1]" in e.value.message
    assert "valid keys" in str(e.value)
    with pytest.raises(DsrlError) as e:
        dsrl_client.load_dataset("OfflineNoSuchTask-v0", progress=False)
    assert e.value.status == 404 and e.value.exit_code == 4


def test_arrays_export_a_multi_pass_policy_for_the_evaluator():
    # A FISOR-form diffusion policy from plain arrays (what flax parameters become with numpy.asarray), its flax
    # Dense layers through flax_dense; tests/e2e/python_package.rs loads it as the evaluator does and plays it.
    rng = np.random.default_rng(3)
    task = dsrl_client.task("OfflineBallRun-v0")
    obs, act, h = task["obs_dim"], task["act_dim"], 16

    def dense(n_in, n_out):
        return {"kernel": rng.normal(0, 0.3, (n_in, n_out)), "bias": rng.normal(0, 0.1, n_out)}

    tensors = {"actor.time.kernel": rng.normal(0, 0.2, (4, 1))}
    for name, (n_in, n_out) in {"actor.cond.0": (8, 16), "actor.cond.1": (16, 16), "actor.input": (act + obs + 16, h),
                                "actor.output": (h, act)}.items():
        tensors.update(dsrl_client.export.flax_dense(dense(n_in, n_out), name))
    for k in range(2):
        tensors[f"actor.blocks.{k}.norm.weight"] = np.ones(h)
        tensors[f"actor.blocks.{k}.norm.bias"] = np.zeros(h)
        tensors.update(dsrl_client.export.flax_dense(dense(h, 4 * h), f"actor.blocks.{k}.expand"))
        tensors.update(dsrl_client.export.flax_dense(dense(4 * h, h), f"actor.blocks.{k}.project"))
    for j in range(2):
        for i, (n_in, n_out) in enumerate([(obs + act, 32), (32, 32), (32, 1)]):
            tensors.update(dsrl_client.export.flax_dense(dense(n_in, n_out), f"cost_q.{j}.{i}"))
    architecture = {"name": "diffusion", "time_dim": 8, "cond_sizes": [16, 16], "hidden_dim": h, "num_blocks": 2,
                    "layer_norm": True, "critic_hidden_sizes": [32, 32], "critic_members": 2, "max_action": 1.0,
                    "sampler": {"kind": "ddpm", "steps": 5, "beta_min": 0.1, "beta_max": 10.0, "clip": True,
                                "temperature": 1.0, "candidates": 16, "choice": "min_cost_q"}}
    out = os.environ["DSRL_TEST_EXPORT"]
    config = dsrl_client.export.export_arrays(tensors, task="OfflineBallRun-v0", architecture=architecture,
                                              out_dir=out)
    assert config["conditioning"] == {"kind": "unconditioned"} and config["obs_dim"] == obs
    raw = open(os.path.join(out, "policy.safetensors"), "rb").read()
    header = json.loads(raw[8:8 + int.from_bytes(raw[:8], "little")])
    assert header["actor.input.weight"] == {"dtype": "F32", "shape": [h, act + obs + 16],
                                            "data_offsets": header["actor.input.weight"]["data_offsets"]}
    assert len(header) == len(tensors)


def test_upload_waits_out_a_conversion_longer_than_the_timeout_and_a_retry_sends_nothing(monkeypatch):
    upload = json.loads(os.environ["DSRL_TEST_UPLOAD"])
    with pytest.raises(DsrlError) as e:
        dsrl_client.upload(upload["path"], task=upload["task"], token="not-the-admin-token", progress=False)
    assert e.value.status in (401, 403) and e.value.code in ("unauthenticated", "permission_denied"), e.value.code
    with pytest.raises(ValueError):
        monkeypatch.delenv("DSRL_ADMIN_TOKEN")
        dsrl_client.upload(upload["path"], task=upload["task"], progress=False)
    monkeypatch.undo()
    # One second for the server's next bytes: the conversion takes longer, and the upload still finishes.
    monkeypatch.setenv("DSRL_CLIENT_TIMEOUT", "1")
    done = dsrl_client.upload(upload["path"], task=upload["task"], tags=["full"], keep_latest=True, progress=False)
    assert done["created"] is True and done["version"]["version"] == upload["version"], done
    assert "full" in done["version"]["tags"] and "latest" not in done["version"]["tags"], done
    again = dsrl_client.upload(upload["path"], task=upload["task"], progress=False)
    assert again["created"] is False and again["version"]["version"] == upload["version"], again
    data = dsrl_client.load_dataset(upload["task"], "full", progress=False)
    assert len(data["rewards"]) == again["version"]["transitions"]


def test_gym_make_gives_dsrls_env_interface():
    ball = VERSIONS["ball"]
    env = gym.make(ball["task"], version=ball["version"])
    assert isinstance(env, dsrl_client.OfflineEnv)
    data = env.get_dataset()
    assert data.version == ball["version"]
    env.set_target_cost(20)
    info = dsrl_client.task(ball["task"])
    r, c = env.get_normalized_score(info["max_episode_reward"], 10.0)
    assert (r, c) == (1.0, 0.5)
    env.set_target_cost(0)
    assert env.get_normalized_score(0.0, 1.0)[1] == 2.0  # DSRL adds one to both when the target is 0
    # No filter: the same arrays back, as DSRL's reassembly gives equal arrays.
    same = env.pre_process_data(data)
    for key in KEYS:
        np.testing.assert_array_equal(same[key], data[key])


def test_pre_process_data_refuses_what_the_server_cannot_have_served():
    ball = VERSIONS["ball"]
    env = gym.make(ball["task"], version=ball["version"])
    data = env.get_dataset()
    with pytest.raises(TypeError, match="get_dataset"):
        env.pre_process_data(dict(data), density=0.5)
    data["rewards"] = data["rewards"] * 2
    with pytest.raises(ValueError, match="changed after it was served"):
        env.pre_process_data(data, density=0.5)
    with pytest.raises(AssertionError, match="set_target_cost"):
        env.pre_process_data(env.get_dataset(), outliers_percent=0.05)


def test_the_env_without_its_simulator_names_the_pip_packages():
    try:
        import dsrl_sim  # noqa: F401
        pytest.skip("the simulator adapter is installed here")
    except ImportError:
        pass
    env = gym.make("OfflineCarCircle1Gymnasium-v0")
    with pytest.raises(dsrl_client.SimulatorMissing, match="safety-gymnasium==1.0.0"):
        env.reset(seed=0)
    with pytest.raises(dsrl_client.SimulatorMissing, match="metadrive-simulator==0.4.3"):
        gym.make("OfflineMetadrive-easysparse-v0").reset(seed=0)


def test_infos_has_dsrls_density_presets_under_dsrls_keys():
    """OSRL's scripts read `DENSITY_CFG[task + "_density" + str(density)]` from `dsrl.infos`."""
    import csv
    from pathlib import Path

    from dsrl_client.infos import DENSITY_CFG

    path = Path(__file__).resolve().parents[3] / "data" / "density_presets.csv"
    rows = list(csv.DictReader(open(path)))
    assert len(DENSITY_CFG) == len(rows) > 0
    for row in rows:
        preset = DENSITY_CFG[row["offline_env_id"] + "_density" + str(float(row["density"]))]
        assert preset == {k: int(row[k]) for k in ("cbins", "rbins", "max_npb", "min_npb")}


CASES = [c for c in GOLDEN["cases"] if c["dataset"] in VERSIONS]


@pytest.mark.parametrize("case", CASES, ids=[f"{c['dataset']}:{c['filter']}" for c in CASES])
def test_pre_process_data_equals_dsrls_own_output(case):
    """DSRL's `pre_process_data` (0.1.0 with the current bounds, tests/golden/make_golden.py) on the same dataset,
    called the way DSRL users call it; the server's filtered version must be its output bit for bit."""
    source = VERSIONS[case["dataset"]]
    env = gym.make(source["task"], version=source["version"])
    data = env.get_dataset()
    target = case["target_cost"]
    env.set_target_cost(target if target is not None else env.cost_thresholds[0])
    expected = case["expected"]
    random.seed(12345)  # the package never draws from Python's global random: `seed` is explicit
    kwargs = dict(case["kwargs"])
    if "inpaint_ranges" in kwargs:
        kwargs["inpaint_ranges"] = [tuple(r) for r in kwargs["inpaint_ranges"]]
    if "error" in expected:
        with pytest.raises((DsrlError, AssertionError)):
            env.pre_process_data(data, **kwargs, seed=case["seed"])
        return
    out = env.pre_process_data(data, **kwargs, seed=case["seed"])
    assert len(out["rewards"]) == expected["rows"]
    assert int(np.sum(out["terminals"] | out["timeouts"])) == expected["episodes"]
    for key in KEYS:
        assert digest(out[key]) == expected["sha256"][key], key
