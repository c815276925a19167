//! The simulator worker. It embeds CPython (pyo3) and serves the `Simulator` gRPC service of
//! `proto/dsrl/simulator/v1/simulator.proto`: sessions of K environments of one task, stepped in batches, with
//! tensors as raw bytes. The RPC layer is Rust because Python's grpcio costs more CPU per call than a simulator
//! step (see BENCHMARKS.md); the simulators themselves are the pinned Python packages of `sim/python`.
//!
//! `run(listener, config, shutdown)` is the whole worker; `dsrl-sim-worker` wraps it with flags.

pub mod acting;
pub mod error;
pub mod memory;
pub mod python;
pub mod random_actions;
pub mod service;
pub mod session;

use std::future::Future;

use dsrl_proto::simulator::v1::simulator_server::SimulatorServer;
use dsrl_suite::catalog::Catalog;
use tokio::net::TcpListener;
use tokio_stream::StreamExt;
use tokio_stream::wrappers::TcpListenerStream;

pub use error::SimError;
pub use python::PythonPaths;
pub use session::Limits;

pub struct WorkerConfig {
    pub paths: PythonPaths,
    pub limits: Limits,
    pub catalog: Catalog,
}

/// Starts the embedded Python (once per process), then serves until `shutdown` completes.
pub async fn run(
    listener: TcpListener,
    config: WorkerConfig,
    shutdown: impl Future<Output = ()>,
) -> anyhow::Result<()> {
    run_announced(listener, config, async {}, shutdown).await
}

/// `run`, awaiting `ready` once Python is up and just before serving (the binary prints its address there).
pub async fn run_announced(
    listener: TcpListener,
    config: WorkerConfig,
    ready: impl Future<Output = ()>,
    shutdown: impl Future<Output = ()>,
) -> anyhow::Result<()> {
    let paths = config.paths.clone();
    let (python, host) = tokio::task::spawn_blocking(move || python::PythonThread::start(&paths)).await??;
    let service = service::SimulatorService::new(python, host, config.catalog, config.limits);
    ready.await;
    // Small messages in lockstep: Nagle's algorithm would add delayed-ACK stalls to every K=1 step.
    let incoming = TcpListenerStream::new(listener).map(|stream| {
        stream.inspect(|s| {
            let _ = s.set_nodelay(true);
        })
    });
    tonic::transport::Server::builder()
        .add_service(
            SimulatorServer::new(service)
                .max_decoding_message_size(256 << 20)
                .max_encoding_message_size(256 << 20),
        )
        .serve_with_incoming_shutdown(incoming, shutdown)
        .await?;
    Ok(())
}
