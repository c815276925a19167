//! `dsrl-sim-worker`: hosts the benchmark simulators behind the batched `Simulator` gRPC protocol.

use std::net::SocketAddr;
use std::path::PathBuf;

use clap::Parser;
use dsrl_sim::{Limits, PythonPaths, WorkerConfig};
use dsrl_suite::catalog::Catalog;

/// Serves the 38 benchmark tasks' simulators (Bullet-Safety-Gym, Safety-Gymnasium, MetaDrive) over gRPC.
///
/// Once listening it prints one line, `dsrl-sim-worker listening on ADDR`, so a parent process (the dsrl-server's
/// worker pool) can start it on port 0 and learn the port. The simulators run in an embedded CPython with the
/// environment that `sim/setup.sh` creates.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    /// Address to listen on; port 0 picks a free port.
    #[arg(long, default_value = "127.0.0.1:0", env = "DSRL_SIM_LISTEN")]
    listen: SocketAddr,
    /// The simulator virtual environment made by sim/setup.sh.
    #[arg(long, env = "DSRL_SIM_VENV", default_value = concat!(env!("CARGO_MANIFEST_DIR"), "/../.venv-sim"))]
    venv: PathBuf,
    /// The folder holding the dsrl_sim Python package.
    #[arg(long, env = "DSRL_SIM_SOURCE", default_value = concat!(env!("CARGO_MANIFEST_DIR"), "/python"))]
    python_source: PathBuf,
    /// Most environments one session may open.
    #[arg(long, default_value_t = 64)]
    max_envs_per_session: u32,
    /// Most environments over all sessions of this worker.
    #[arg(long, default_value_t = 256)]
    max_envs: u32,
    /// Exit when standard input closes: a parent that dies (even by SIGKILL) takes its workers with it.
    #[arg(long)]
    exit_with_stdin: bool,
    /// Task catalog CSV (default: the catalog built into the binary, data/tasks.csv).
    #[arg(long)]
    tasks: Option<PathBuf>,
    /// Tests only: `short-step-answers=N` makes the next N step answers leave out a row (play answers: their ended
    /// episodes).
    #[arg(long, hide = true)]
    inject_fault: Option<String>,
}

// One runtime thread: it only moves gRPC messages, while the simulators run on their own Python thread
// (python.rs). A multi-threaded runtime adds cross-thread wake-ups to every step answer and, on a machine whose
// cores the evaluator, its policy processes and the other workers share, costs CPU (BENCHMARKS.md, scoring).
fn main() -> anyhow::Result<()> {
    // A session's policy (`Act`) runs candle's kernels on the Python thread that steps the simulators, one thread,
    // as the server's policy processes do.
    // SAFETY: first thing in main, before any other thread exists.
    unsafe { dsrl_policy::pin_candle_threads() };
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?
        .block_on(serve())
}

async fn serve() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".parse().expect("filter")),
        )
        .with_writer(std::io::stderr)
        .init();
    dsrl_sim::memory::keep_freed_memory();
    let args = Args::parse();
    if let Some(fault) = &args.inject_fault {
        let n = fault
            .strip_prefix("short-step-answers=")
            .and_then(|n| n.parse().ok())
            .ok_or_else(|| anyhow::anyhow!("unknown fault {fault:?}; the one fault is short-step-answers=N"))?;
        dsrl_sim::service::inject_short_step_answers(n);
    }
    let catalog = match &args.tasks {
        Some(path) => Catalog::load(path)?,
        None => Catalog::embedded()?,
    };
    let config = WorkerConfig {
        paths: PythonPaths {
            source: args.python_source,
            venv: args.venv,
        },
        limits: Limits {
            max_envs_per_session: args.max_envs_per_session,
            max_envs: args.max_envs,
        },
        catalog,
    };
    let listener = tokio::net::TcpListener::bind(args.listen).await?;
    let addr = listener.local_addr()?;
    if args.exit_with_stdin {
        std::thread::spawn(|| {
            let _ = std::io::copy(&mut std::io::stdin().lock(), &mut std::io::sink());
            tracing::info!("standard input closed: exiting");
            // Nothing here is durable; MetaDrive children exit on their own when their pipes close.
            std::process::exit(0);
        });
    }
    let shutdown = async {
        let mut terminate =
            tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()).expect("SIGTERM handler");
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {}
            _ = terminate.recv() => {}
        }
    };
    // Python starts inside run(); announce the address only once it is ready to serve.
    let ready = async move {
        println!("dsrl-sim-worker listening on {addr}");
        tracing::info!(%addr, "listening");
    };
    dsrl_sim::run_announced(listener, config, ready, shutdown).await
}
