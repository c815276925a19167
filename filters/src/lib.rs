//! DSRL's post-process filters (`OfflineEnv.pre_process_data`), reproduced bit for bit: the density (grid) filter,
//! tempting outliers, inpainting (partial discarding), epsilon discarding and observation noise, with the exact
//! random streams of the reference (CPython's `random` for the density filter, NumPy's `Generator(PCG64(1234))`
//! for outliers and noise) and NumPy 1.24's float32 arithmetic.

pub mod apply;
pub mod plan;
pub mod spec;

/// What filtered datasets reproduce: DSRL's own code ("upstream", docs/glossary.md). The text is recorded in every
/// filtered version's provenance (its `reference` field, the name clients read), so it stays as first written.
pub const UPSTREAM: &str = "DSRL OfflineEnv.pre_process_data with the current reference's bounds (GitHub HEAD), \
NumPy 1.24 and CPython random semantics";
