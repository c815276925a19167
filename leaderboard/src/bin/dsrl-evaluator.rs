//! `dsrl-evaluator`: the leaderboard's evaluator process (see `dsrl_leaderboard::evaluator`).

use clap::Parser;
use dsrl_service::ProcessArgs;

/// Score leaderboard submissions: claim jobs from the shared database (database.url) and play them on this
/// process's simulator workers, `leaderboard.evaluators` at once (at least one). Run it beside API replicas
/// (`dsrl-server` with DSRL__LEADERBOARD__EVALUATORS=0) that share the database, the object store and the secrets;
/// scale it apart from them. It serves only /healthz and /metrics on --listen and links neither the REST/gRPC API
/// nor the dataset storage.
///
/// Configuration is dsrl-server's (the same TOML file and DSRL__SECTION__KEY variables; see deploy/README.md):
/// database.url, storage, simulators, leaderboard.seed_secret, auth.admin_token. On start it prints one line
/// "dsrl-evaluator listening on http://ADDR" to stdout; SIGTERM stops it after the episodes in flight (an
/// interrupted job goes back to the queue when its lease lapses).
#[derive(Debug, Parser)]
#[command(version)]
struct Args {
    #[command(flatten)]
    process: ProcessArgs,
}

fn main() -> std::process::ExitCode {
    // A submitted policy's child process (`play-policy`, started by this evaluator).
    // SAFETY: first thing in this process, before any other thread exists.
    if let Some(code) = unsafe { dsrl_evaluation::inference::serve_child_if_started_as_one() } {
        return code;
    }
    let args = Args::parse();
    dsrl_service::init_logging(args.process.log_json);
    let runtime = tokio::runtime::Runtime::new().expect("starting the async runtime");
    match runtime.block_on(evaluate(args)) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!("{e:#}");
            eprintln!("dsrl-evaluator: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

async fn evaluate(args: Args) -> anyhow::Result<()> {
    let config = args.process.load_config(None)?;
    let listener = tokio::net::TcpListener::bind(config.server.listen).await?;
    let addr = listener.local_addr()?;
    tracing::info!(%addr, "evaluator");
    println!("dsrl-evaluator listening on http://{addr}");
    let program = std::env::current_exe()?;
    dsrl_leaderboard::evaluator::run(listener, config, Some(program), dsrl_service::shutdown_signal()).await?;
    tracing::info!("stopped");
    Ok(())
}
