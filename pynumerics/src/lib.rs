//! CPython's and NumPy's random numbers and the few float operations DSRL's Python code depends on, reproduced bit
//! for bit, so that what DSRL's code computed from a seed is computed here from the same seed: CPython's MT19937
//! (`random.sample`, `random.random`; `pyrandom`), NumPy's SeedSequence, PCG64, bounded integers, `Generator.choice`
//! and ziggurat normals (`nprandom`), and NumPy 1.24's float floor division, float32 pairwise sums and `np.std`
//! (`numpy_math`). The filters (`dsrl-filters`), the FSRL trajectory buffer (`dsrl_suite::collection`) and the
//! leaderboard's bootstrap (`dsrl-scoring`) draw from them.
//!
//! The ziggurat tables were measured through NumPy's public API (`tests/golden/ziggurat_probe.py`), not copied.

pub mod nprandom;
pub mod numpy_math;
pub mod pyrandom;
mod ziggurat_tables;
