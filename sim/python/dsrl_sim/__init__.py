"""Simulator hosting for dsrl workers.

`tasks.make_env(sim_id)` builds any of the 38 benchmark tasks' simulators behind one interface (reset with a seed,
step with an action, cost as the simulator reports it); `batch.Batch` steps K of them with inputs and outputs packed
as raw bytes, which is what the Rust worker passes across the embedding boundary.
"""
