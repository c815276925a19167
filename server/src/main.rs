//! `dsrl-server`: the dsrl service on one port (REST + gRPC).

use std::path::PathBuf;

use clap::{Parser, Subcommand};
use dsrl_evaluation::limit_memory;
use dsrl_server::datasets::converter::{ConvertReply, Converter, exit_when_stdin_closes};
use dsrl_service::ProcessArgs;

/// Serve offline safe-RL datasets: the 38-task catalog, versioned Parquet datasets, downloads with resume.
///
/// Configuration layers, later ones win: built-in defaults (SQLite and a local object store under
/// ~/.dsrl/server, starter datasets from ./data/starter) → the TOML file given with --config → environment
/// variables DSRL__SECTION__KEY (e.g. DSRL__SERVER__LISTEN=0.0.0.0:7070, DSRL__STORAGE__BACKEND=s3,
/// DSRL__STORAGE__S3__BUCKET=...) → the flags below. See deploy/README.md for every key.
///
/// The admin token (for ingest and tags) is auth.admin_token, or else generated into <data_dir>/admin-token.
/// On start the server prints one line "dsrl-server listening on http://ADDR" to stdout.
///
/// Several API replicas and evaluator processes (`dsrl-evaluator`) can share one PostgreSQL database (database.url)
/// and one S3 bucket: see deploy/README.md.
#[derive(Debug, Parser)]
#[command(version)]
struct Args {
    #[command(flatten)]
    process: ProcessArgs,
    /// Folder of starter datasets to ingest at start-up when missing.
    #[arg(long)]
    starter_datasets: Option<PathBuf>,
    #[command(subcommand)]
    command: Option<Internal>,
}

/// Roles other than the API, and internal commands the server runs itself.
#[derive(Debug, Subcommand)]
enum Internal {
    /// Remove filtered versions by the gc policy (gc.derived_max_idle_hours, gc.derived_max_bytes): those unused
    /// for longer first, then the least recently used until all fit the size budget. With PostgreSQL it is safe
    /// while servers run on the same database and store (it takes their locks); with the embedded SQLite default,
    /// whose locks live inside the one server process, stop that server first. A removed filter is computed again
    /// when asked for. Prints a JSON report.
    Gc {
        /// Report what would be removed, remove nothing.
        #[arg(long)]
        dry_run: bool,
    },
    /// Convert one upload to the canonical layout in this (child) process and answer with one JSON line.
    #[command(hide = true)]
    Convert {
        #[arg(long)]
        task: String,
        #[arg(long)]
        observation_space: dsrl_suite::ObservationSpace,
        #[arg(long)]
        memory_limit: u64,
        source: PathBuf,
        out: PathBuf,
    },
}

fn main() -> std::process::ExitCode {
    // A submitted policy's child process (`play-policy`, started by this server's evaluators).
    // SAFETY: first thing in this process, before any other thread exists.
    if let Some(code) = unsafe { dsrl_evaluation::inference::serve_child_if_started_as_one() } {
        return code;
    }
    let args = Args::parse();
    if let Some(Internal::Convert {
        task,
        observation_space,
        memory_limit,
        source,
        out,
    }) = &args.command
    {
        return convert(task, *observation_space, *memory_limit, source, out);
    }
    let runtime = tokio::runtime::Runtime::new().expect("starting the async runtime");
    runtime.block_on(server_main(args))
}

/// The child side of upload conversion (see `storage::converter`).
fn convert(
    task: &str,
    space: dsrl_suite::ObservationSpace,
    memory_limit: u64,
    source: &std::path::Path,
    out: &std::path::Path,
) -> std::process::ExitCode {
    exit_when_stdin_closes();
    limit_memory(memory_limit);
    let reply = match dsrl_suite::Catalog::embedded()
        .map_err(|e| e.to_string())
        .and_then(|c| c.get(task).cloned().map_err(|e| e.to_string()))
    {
        Ok(task) => ConvertReply::run(source, &task, space, out),
        Err(message) => ConvertReply::Failed { message },
    };
    println!("{}", serde_json::to_string(&reply).expect("the reply serializes"));
    std::process::ExitCode::SUCCESS
}

async fn server_main(args: Args) -> std::process::ExitCode {
    dsrl_service::init_logging(args.process.log_json);
    match serve(args).await {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!("{e:#}");
            eprintln!("dsrl-server: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

async fn serve(args: Args) -> anyhow::Result<()> {
    let config = args.process.load_config(args.starter_datasets)?;
    if let Some(Internal::Gc { dry_run }) = args.command {
        let report = dsrl_server::run_gc(&config, dry_run).await?;
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    let listener = tokio::net::TcpListener::bind(config.server.listen).await?;
    let addr = listener.local_addr()?;
    let converter = Converter::Subprocess {
        program: std::env::current_exe()?,
        memory_limit_bytes: config.datasets.converter_memory_limit_bytes,
    };
    let state = dsrl_server::build_state(&config, converter).await?;
    tracing::info!(%addr, data_dir = %config.server.data_dir.display(), "serving");
    println!("dsrl-server listening on http://{addr}");
    dsrl_server::serve_until(listener, state, dsrl_service::shutdown_signal()).await?;
    tracing::info!("stopped");
    Ok(())
}
