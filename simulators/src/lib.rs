//! Talking to the simulator workers (`dsrl-sim-worker`, see `sim/`): the typed client of one session (`session`:
//! open K environments, reset, step, drive, render, with every answer checked against its request) and the pool
//! that places sessions on workers (`pool`: local workers started and replaced when they die, remote ones
//! health-checked, services re-resolved; `pooled`: a session on a pool worker with per-request deadlines and errors
//! that name the worker; `python_package`: whether the workers' simulator Python is the build's). The evaluators, the data pipeline and the server's status route use it; the tests and the
//! benchmarks drive workers through `session` directly.

mod config;
mod error;
mod pool;
mod pooled;
mod python_package;
pub mod session;

pub use config::SimulatorsConfig;
pub use error::SimulatorError;
pub use pool::{SimulatorPool, WorkerStatus};
pub use pooled::{PooledSession, split_in_two};
pub use python_package::{label_with_workers_python, mark_modified};
pub use session::{DrivenRest, Played, PlayedEpisode, RenderedFrames, Reply, SimulatorSession, StepResult};
