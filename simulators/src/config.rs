use std::path::PathBuf;

use serde::{Deserialize, Serialize};

/// The simulator worker pool (`dsrl-sim-worker` processes) that evaluation and data collection step.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimulatorsConfig {
    /// Workers started with the server and replaced when they die (0: none).
    pub local_workers: u32,
    /// The worker binary; unset means `dsrl-sim-worker` beside the `dsrl-server` executable.
    pub worker_binary: Option<PathBuf>,
    /// Extra flags for local workers, e.g. `["--venv", "/opt/dsrl/venv-sim"]`.
    pub worker_args: Vec<String>,
    /// `host:port` of workers started elsewhere; health-checked, never restarted by this server.
    pub remote_workers: Vec<String>,
    /// `host:port` names resolved again every `discovery_interval_ms`; every address one resolves to is a remote
    /// worker, added when it appears and retired when it is gone (a Kubernetes headless Service resolves to one
    /// address per ready pod).
    pub worker_services: Vec<String>,
    /// Time between two resolutions of `worker_services`.
    pub discovery_interval_ms: u64,
    /// Time between health checks of each worker.
    pub health_interval_ms: u64,
    /// A session request (open, reset, step) that takes longer than this, times the sessions open on its worker
    /// (which answers them one after another), fails its session.
    pub request_timeout_s: u64,
}

impl Default for SimulatorsConfig {
    fn default() -> Self {
        SimulatorsConfig {
            local_workers: 2,
            worker_binary: None,
            worker_args: Vec::new(),
            remote_workers: Vec::new(),
            worker_services: Vec::new(),
            discovery_interval_ms: 5000,
            health_interval_ms: 1000,
            request_timeout_s: 120,
        }
    }
}
