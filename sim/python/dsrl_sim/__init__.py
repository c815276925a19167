"""Simulator hosting for dsrl workers.

`tasks.make_env(sim_id)` builds any of the 38 benchmark tasks' simulators behind one interface (reset with a seed,
step with an action, cost as the simulator reports it); `batch.Batch` steps K of them with inputs and outputs packed
as raw bytes, which is what the Rust worker passes across the embedding boundary.
"""

import os as _os

# One worker runs per core and steps its environments one after another, so NumPy's BLAS must not start a thread
# per core of its own: on a 2-core machine those threads spin in sched_yield against the other worker and the
# server (measured: a 60-episode BallCircle loop spent 7.9 s in the kernel with them, 0.2 s without). Set before
# any simulator imports NumPy; a caller's explicit choice wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
