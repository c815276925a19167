//! `dsrl-admin`: building datasets from recipes.

use std::path::PathBuf;

use clap::{Parser, Subcommand};
use dsrl_client::api::{Client, IngestOptions};
use dsrl_pipeline::build::Run;
use dsrl_pipeline::recipe::Recipe;
use dsrl_server::config::SimulatorsConfig;
use dsrl_suite::Catalog;

#[derive(Parser, Debug)]
#[command(
    version,
    about = "Builds dsrl datasets on the real simulators from the recipes under data/recipes."
)]
struct Args {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Collect a task's dataset with its recipe, then (with --server) ingest it as a new version.
    ///
    /// Starts its own simulator workers (dsrl-sim-worker beside this binary). MetaDrive recipes run their IDM
    /// sweep settings in parallel and keep every finished setting in the state folder; Bullet and Safety-Gymnasium
    /// recipes train a PPO-Lagrangian expert while its cost limit sweeps, keep what it plays in the trajectory
    /// buffer and save everything periodically (expert/ in the state folder, with expert/training.csv and the
    /// final expert policy in expert/policy). A run that is killed resumes where it stopped when started again
    /// with the same folder. The result is deterministic for a recipe, its seed and the budget.
    /// Output: <state>/<prefix>-<cost cap>-<episodes>.parquet and <that name>.provenance.json.
    Collect {
        /// Offline task id, e.g. OfflineMetadrive-easysparse-v0.
        #[arg(long)]
        task: String,
        /// Recipe file (default: data/recipes/<task>.toml).
        #[arg(long)]
        recipe: Option<PathBuf>,
        /// State and output folder (default: ~/.dsrl/collect/<task>).
        #[arg(long)]
        state: Option<PathBuf>,
        /// Scale an IDM sweep's budget: episodes per sweep setting instead of the recipe's.
        #[arg(long)]
        episodes_per_setting: Option<u32>,
        /// Scale an expert recipe's budget: environment steps to train for instead of the recipe's budget_steps
        /// (the cost-limit schedule is compressed or stretched to fit).
        #[arg(long)]
        budget_steps: Option<u64>,
        /// Local simulator workers (default: one per core).
        #[arg(long)]
        workers: Option<u32>,
        /// Environments per worker session (MetaDrive: one process each, ~300 MB).
        #[arg(long, default_value_t = 4)]
        envs_per_session: u32,
        /// Thin the result to at most N episodes, spread over the (reward, cost) plane like the trajectory buffer
        /// does (for starter datasets; a finished run's settings are reused, nothing is simulated again).
        #[arg(long)]
        max_episodes: Option<usize>,
        /// Output folder (default: the state folder).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Worker binary (default: dsrl-sim-worker beside dsrl-admin).
        #[arg(long)]
        worker_binary: Option<PathBuf>,
        /// Ingest the result into this dsrl-server (admin token from --token or DSRL_ADMIN_TOKEN).
        #[arg(long, env = "DSRL_SERVER")]
        server: Option<String>,
        #[arg(long, env = "DSRL_ADMIN_TOKEN", hide_env_values = true)]
        token: Option<String>,
        /// Tags to point at the ingested version besides latest.
        #[arg(long)]
        tag: Vec<String>,
        /// Print the result as JSON.
        #[arg(long)]
        json: bool,
    },
}

fn main() -> anyhow::Result<()> {
    // SAFETY: first thing in main, before the runtime or any other thread exists.
    unsafe { dsrl_policy::pin_candle_threads() };
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?
        .block_on(run())
}

async fn run() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("DSRL_LOG").unwrap_or_else(|_| "warn".parse().expect("filter")),
        )
        .with_writer(std::io::stderr)
        .init();
    let Command::Collect {
        task,
        recipe,
        state,
        episodes_per_setting,
        budget_steps,
        workers,
        envs_per_session,
        worker_binary,
        max_episodes,
        out,
        server,
        token,
        tag,
        json,
    } = Args::parse().command;
    let catalog = Catalog::embedded()?;
    let recipe_path = recipe.unwrap_or_else(|| Recipe::default_path(&task));
    let recipe = Recipe::load(&recipe_path)?;
    anyhow::ensure!(
        recipe.task == task,
        "{} is the recipe of {}, not {task}",
        recipe_path.display(),
        recipe.task
    );
    let home = std::env::var_os("HOME").map(PathBuf::from).unwrap_or_default();
    let state_dir = state.unwrap_or_else(|| home.join(".dsrl/collect").join(&task));
    let cores = std::thread::available_parallelism()
        .map(|n| n.get() as u32)
        .unwrap_or(1);
    let run = Run {
        recipe,
        recipe_path,
        state_dir,
        episodes_per_setting,
        budget_steps,
        workers: workers.unwrap_or(cores).max(1),
        envs_per_session: envs_per_session.max(1),
        simulators: SimulatorsConfig {
            worker_binary,
            ..SimulatorsConfig::default()
        },
        progress: !json,
        max_episodes,
        out_dir: out,
    };
    let built = run.execute(&catalog).await?;
    let mut report = serde_json::json!({
        "task": task,
        "file": built.path,
        "version": built.converted.version.to_string(),
        "episodes_collected": built.collected,
        "episodes_after_buffer": built.after_buffer,
        "episodes": built.converted.episode_index.len(),
        "provenance": built.provenance,
    });
    if let Some(server) = server {
        let client = Client::new(&server)?.with_token(token);
        let options = IngestOptions {
            tags: tag,
            provenance_json: Some(serde_json::to_string(&built.provenance)?),
            ..IngestOptions::default()
        };
        let ingested = client.ingest(&task, &built.path, &options, |_| {}).await?;
        report["ingested"] = serde_json::json!({ "created": ingested.created, "manifest_url": ingested.manifest_url });
    }
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "{task}: {} episodes ({} collected) -> {} (version {})",
            built.converted.episode_index.len(),
            built.collected,
            built.path.display(),
            built.converted.version
        );
        if let Some(url) = report.get("ingested").and_then(|i| i["manifest_url"].as_str()) {
            println!("ingested: {url}");
        }
    }
    Ok(())
}
