//! Client library of the dsrl service and the `dsrl-client` CLI built on it.
//!
//! - [`api::Client`]: the REST API (catalog, manifests, downloads, admin ingest and tags).
//! - [`cache::Cache`]: the local dataset cache under `$DSRL_DATASET_DIR` or `~/.dsrl/datasets`, with verified,
//!   resumable, lock-protected fetches and a full re-hash (`verify`).
//! - [`error::ClientError`]: every failure, with the CLI exit code it maps to.

pub mod api;
pub mod cache;
pub mod error;
pub mod output;

pub use api::Client;
pub use cache::{Cache, FetchOptions, FetchOutcome, OutputFormat};
pub use error::ClientError;
