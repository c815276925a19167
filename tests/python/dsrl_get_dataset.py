"""Load an HDF5 file exactly as DSRL's `OfflineEnv.get_dataset(h5path=...)` does (spec §1.1), then compare it with
the Parquet file of the same version read by pyarrow. Prints a JSON summary; exits non-zero on any mismatch.

usage: dsrl_get_dataset.py FILE.hdf5 FILE.parquet OBS_DIM ACT_DIM
"""
import json
import sys

import h5py
import numpy as np
import pyarrow.parquet as pq

KEYS = ["observations", "next_observations", "actions", "rewards", "costs", "terminals", "timeouts"]


def get_dataset(h5path, obs_dim, act_dim):
    data_dict = {}
    with h5py.File(h5path, "r") as dataset_file:
        def collect(name, obj):
            if isinstance(obj, h5py.Dataset):
                try:
                    data_dict[name] = obj[:]
                except ValueError:
                    data_dict[name] = obj[()]
        dataset_file.visititems(collect)
    for key in KEYS:
        assert key in data_dict, f"Dataset is missing key {key}"
    n = data_dict["observations"].shape[0]
    assert data_dict["observations"].shape[1:] == (obs_dim,), data_dict["observations"].shape
    assert data_dict["actions"].shape[1:] == (act_dim,), data_dict["actions"].shape
    for key in ["rewards", "costs", "terminals"]:
        if data_dict[key].shape == (n, 1):
            data_dict[key] = data_dict[key][:, 0]
        assert data_dict[key].shape == (n,), f"{key} shape {data_dict[key].shape}"
    for key in ["observations", "actions", "next_observations", "rewards", "costs"]:
        data_dict[key] = data_dict[key].astype(np.float32)
    return data_dict


def main():
    h5path, parquet_path, obs_dim, act_dim = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    data = get_dataset(h5path, obs_dim, act_dim)
    table = pq.read_table(parquet_path)
    frame = table.to_pandas()  # pandas users need no custom code either
    n = len(frame)
    assert data["observations"].shape[0] == n, (data["observations"].shape, n)
    for key in ["observations", "next_observations", "actions"]:
        column = np.stack(table.column(key).to_numpy(zero_copy_only=False)).astype(np.float32)
        assert np.array_equal(column, data[key]), key
    for key in ["rewards", "costs"]:
        assert frame[key].dtype == np.float32, frame[key].dtype
        assert np.array_equal(frame[key].to_numpy(), data[key]), key
    for key in ["terminals", "timeouts"]:
        assert data[key].dtype == np.bool_, (key, data[key].dtype)
        assert np.array_equal(frame[key].to_numpy(), data[key]), key
    dones = np.logical_or(data["terminals"] == 1, data["timeouts"] == 1)
    episodes = int(dones.sum())
    assert frame["episode"].max() + 1 == episodes
    # DSRL's split: the reward return of each trajectory is np.sum over its float32 slice.
    ends = np.nonzero(dones)[0]
    starts = np.concatenate([[0], ends[:-1] + 1])
    returns = [float(np.sum(data["rewards"][s:e + 1])) for s, e in zip(starts, ends)]
    print(json.dumps({"transitions": n, "episodes": episodes, "reward_returns": returns,
                      "dtypes": {k: str(data[k].dtype) for k in KEYS}}))


if __name__ == "__main__":
    main()
