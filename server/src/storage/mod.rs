//! Where datasets live: Parquet files and manifests in an object store, their metadata and tags in SQLite.
//! `datasets` is the only module that touches both, so the order "file, then manifest, then row" that makes
//! ingest atomic is written in one place.

pub mod converter;
pub mod datasets;
pub mod db;
pub mod objects;
