"""A dataset's vector columns as NumPy matrices, in either layout dsrl writes: a FixedSizeList<f32> column, or the
struct form (one f32 field per dimension, which the committed starters use for observations: each dimension
compresses as a column of its own)."""
import numpy as np
import pyarrow as pa


def matrix(table, name):
    """Column `name` as an (n, d) float32 array, and which rows are null (the compact form leaves next_observations
    out where row t+1 of the same episode starts from it); null rows come back as NaN."""
    arr = table.column(name).combine_chunks()
    nulls = arr.is_null().to_numpy(zero_copy_only=False)
    if pa.types.is_struct(arr.type):
        dims = [np.asarray(c.to_numpy(zero_copy_only=False), dtype=np.float32) for c in arr.flatten()]
        return np.stack(dims, axis=1), nulls
    d = arr.type.list_size
    values = arr.values.to_numpy(zero_copy_only=False)[arr.offset * d:(arr.offset + len(arr)) * d]
    return values.reshape(len(arr), d).astype(np.float32), nulls
