//! The DSRL benchmark suite as a library, shared by the server and the client: the task catalog, typed ids, the
//! Parquet dataset format and its manifest, episode summaries, normalized scores, and DSRL HDF5 import/export.
//!
//! Nothing here does I/O on the network; every function works on local files or in memory so the server can run
//! it on a blocking thread and the client can reuse it offline.

pub mod catalog;
pub mod collection;
pub mod convert;
pub mod croissant;
pub mod episode;
pub mod hashing;
#[cfg(feature = "hdf5")]
pub mod hdf5_file;
pub mod ids;
pub mod manifest;
pub mod names;
pub mod parquet_file;
pub mod plot;
pub mod score;
pub mod synthetic;
pub mod transitions;
pub mod validate;
pub mod writeback;

pub use catalog::{Catalog, CatalogError, Family, ObservationSpace, Task, UnknownTask};
pub use episode::EpisodeSummary;
pub use ids::{IdError, TagName, TaskId, VersionId, VersionRef};
pub use manifest::{HostedVersion, Hosting, Manifest, Provenance};
pub use score::NormalizedScore;
