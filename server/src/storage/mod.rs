//! Where datasets live: Parquet files and manifests in an object store, their metadata and tags in the metadata
//! database. `datasets` is the only module that touches both, so the order "file, then manifest, then row" that
//! makes ingest atomic is written in one place. The database and the object store themselves are opened by
//! `dsrl-service`, which the evaluators share.

pub mod converter;
pub mod datasets;
pub mod uploads;
pub use dsrl_service::{db, objects};
