//! The data pipeline: recipes (`data/recipes/<task>.toml`) that build a task's dataset on the real simulators,
//! stepped through `dsrl-sim` workers.
//!
//! Implemented: DSRL's MetaDrive collection (a noisy IDM driver over a sweep of acceleration factors and target
//! speeds, spec 6.5), FSRL's trajectory buffer and DSRL's final grid filter (spec 6.2, 6.4, in
//! `dsrl_suite::collection`), FSRL's expert training while collecting for Bullet-Safety-Gym and Safety-Gymnasium
//! (PPO-Lagrangian in candle, `expert`), resumable runs, and ingestion with recipe provenance.

pub mod build;
pub mod collect;
pub mod compact;
pub mod docs;
pub mod expert;
pub mod full;
pub mod hosted;
pub mod identities;
pub mod import_dsrl;
pub mod recipe;
#[cfg(test)]
mod typed_numbers;

use std::path::Path;

/// Writes `bytes` to `path` under a temporary name, then renames it: a run killed mid-write leaves the old file or
/// none, never a truncated one that a resumed run would read as its state.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut partial = path.as_os_str().to_owned();
    partial.push(".partial");
    std::fs::write(&partial, bytes)?;
    std::fs::rename(&partial, path)
}
