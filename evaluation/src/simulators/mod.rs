//! The simulator worker pool: `dsrl-sim-worker` processes (see `sim/`) that the evaluator and the data pipeline
//! step. Local workers are started with the server and replaced when they die; remote ones are health-checked.
//! Sessions go to the healthy worker with the most free capacity, and fail fast with the worker's name when it
//! dies under them.

mod pool;
mod session;

pub use dsrl_proto::simulator_session::{RenderedFrames, Reply, StepResult};
pub use pool::{SimulatorPool, WorkerStatus};
pub use session::{PooledSession, split_in_two};
