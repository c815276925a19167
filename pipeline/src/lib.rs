//! The data pipeline: recipes (`data/recipes/<task>.toml`) that build a task's dataset on the real simulators,
//! stepped through `dsrl-sim` workers.
//!
//! Implemented: DSRL's MetaDrive collection (a noisy IDM driver over a sweep of acceleration factors and target
//! speeds, spec 6.5), FSRL's trajectory buffer and DSRL's final grid filter (spec 6.2, 6.4, in
//! `dsrl_suite::collection`), resumable runs, and ingestion with recipe provenance. Not yet: the expert trainers for
//! Bullet-Safety-Gym and Safety-Gymnasium (PPO/TRPO-Lagrangian in candle).

pub mod build;
pub mod collect;
pub mod expert;
pub mod recipe;
