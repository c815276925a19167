//! In-process integration tests of the server crate: `run` on port 0, routing and error rendering through the
//! `app()` router without a socket, and the dataset service under concurrency.

mod ingest;
mod serve;

use std::path::Path;

use dsrl_server::config::Config;

/// A configuration with everything under `dir` and no starter datasets.
pub fn config(dir: &Path) -> Config {
    let mut config = Config::default();
    config.server.data_dir = dir.to_owned();
    config.server.listen = "127.0.0.1:0".parse().unwrap();
    config.datasets.starter_dir = None;
    config.auth.admin_token = Some("integration-test-token".into());
    // The worker pool is tested end to end in tests/e2e/simulators.rs, where the worker binary is built.
    config.simulators.local_workers = 0;
    config
}

/// A synthetic dataset file for `task`.
pub fn dataset(dir: &Path, task: &str, episodes: usize, seed: u64) -> std::path::PathBuf {
    use dsrl_suite::catalog::{Catalog, ObservationSpace};
    let catalog = Catalog::embedded().unwrap();
    let t = catalog.get(task).unwrap();
    let spec = dsrl_suite::synthetic::SyntheticSpec::for_task(t, episodes, seed);
    let path = dir.join(format!("{task}-{seed}.parquet"));
    let chunks = dsrl_suite::synthetic::transitions(spec).map(Ok);
    dsrl_suite::convert::write_canonical(t, ObservationSpace::Simulator, chunks, vec![], &path).unwrap();
    path
}
