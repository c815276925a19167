"""Write a DSRL-layout HDF5 fixture from a Parquet file the way DSRL's own scripts wrote theirs
(`process_dataset.py`: `create_dataset(k, data=np.squeeze(...), compression='gzip')`, float32 values), with the
done flags stored as bool (h5py's enum) or, for older writers, as integers or float. Extra keys can be added, as
MetaDrive's raw collection did.

Bad-input variants for the rejection tests: --nan-at ROW (NaN in observations[ROW, 0]), --unclosed (no done flag
on the last transition), --drop-key KEY, --short-key KEY (one row fewer).

usage: make_dsrl_hdf5.py IN.parquet OUT.hdf5 [--flags bool|int8|float64] [--extra-key NAME] [--column-vectors]
                         [--nan-at ROW] [--unclosed] [--drop-key KEY] [--short-key KEY]
"""
import argparse

import h5py
import numpy as np
import pyarrow.parquet as pq


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("parquet")
    parser.add_argument("out")
    parser.add_argument("--flags", default="bool", choices=["bool", "int8", "float64"])
    parser.add_argument("--extra-key")
    parser.add_argument("--column-vectors", action="store_true", help="store rewards/costs as (N, 1)")
    parser.add_argument("--nan-at", type=int)
    parser.add_argument("--unclosed", action="store_true")
    parser.add_argument("--drop-key")
    parser.add_argument("--short-key")
    args = parser.parse_args()
    table = pq.read_table(args.parquet)
    arrays = {}
    for key in ["observations", "next_observations", "actions"]:
        arrays[key] = np.stack(table.column(key).to_numpy(zero_copy_only=False)).astype(np.float32)
    for key in ["rewards", "costs"]:
        arrays[key] = table.column(key).to_numpy().astype(np.float32)
        if args.column_vectors:
            arrays[key] = arrays[key][:, None]
    for key in ["terminals", "timeouts"]:
        arrays[key] = table.column(key).to_numpy(zero_copy_only=False).astype(args.flags)
    if args.nan_at is not None:
        arrays["observations"][args.nan_at, 0] = np.nan
    if args.unclosed:
        arrays["terminals"][-1] = 0
        arrays["timeouts"][-1] = 0
    if args.short_key:
        arrays[args.short_key] = arrays[args.short_key][:-1]
    if args.drop_key:
        del arrays[args.drop_key]
    with h5py.File(args.out, "w") as out:
        for key, array in arrays.items():
            out.create_dataset(key, data=array, compression="gzip")
        if args.extra_key:
            out.create_dataset(args.extra_key, data=table.column("costs").to_numpy(), compression="gzip")


if __name__ == "__main__":
    main()
