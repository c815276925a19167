//! `dsrl-admin`: building datasets from recipes.

use std::path::PathBuf;

use clap::{Parser, Subcommand};
use dsrl_client::api::{Client, IngestOptions};
use dsrl_evaluation::SimulatorsConfig;
use dsrl_pipeline::build::Run;
use dsrl_pipeline::recipe::Recipe;
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
    Collect(CollectArgs),
    /// Score a policy checkpoint (policy.json + policy.safetensors, e.g. an expert's <state>/expert/policy) on the
    /// real simulators: one episode per seed with the policy's deterministic actions, then the mean returns and the
    /// normalized reward and cost at each of the task's benchmark thresholds (safe iff normalized cost <= 1).
    /// A per-threshold checkpoint is scored at its threshold; a conditioned one (target_cost, returns_to_go) plays
    /// its episodes at each threshold in turn, or at --cost-threshold.
    Evaluate(EvaluateArgs),
    /// Rewrite a dataset (a committed starter, or its parts in order) in the compact form the starters are
    /// committed in: the same rows, so ingest gives the same version id, checked before anything is replaced.
    /// For starters cut before that form existed (with next_observations, observations as lists) it takes about
    /// half the bytes. In place by default: the files given are replaced by the result.
    Compact(CompactArgs),
}

#[derive(clap::Args, Debug)]
struct CompactArgs {
    /// The task the dataset belongs to; its rows are validated against it.
    #[arg(long)]
    task: String,
    /// The dataset file, or the parts of one (<stem>.part-I-of-N.parquet) in order.
    #[arg(required = true)]
    files: Vec<PathBuf>,
    /// Folder for the result, with the dataset's name (default: the files' own folder, replacing them).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write the result as this many files of whole episodes (<stem>.part-I-of-N.parquet).
    #[arg(long, default_value_t = 1)]
    parts: usize,
    /// Print a JSON report instead of a summary line.
    #[arg(long)]
    json: bool,
}

fn compact(args: CompactArgs) -> anyhow::Result<()> {
    let catalog = Catalog::embedded()?;
    let task = catalog.get(&args.task)?;
    let out = match args.out {
        Some(out) => out,
        None => args.files[0]
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(std::path::Path::new("."))
            .to_owned(),
    };
    let done = dsrl_pipeline::compact::rewrite(task, &args.files, &out, args.parts)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&done)?);
    } else {
        println!(
            "{}: {} episodes, version {} kept; {} bytes -> {} bytes in {} file(s) under {}",
            task.id,
            done.episodes,
            done.version,
            done.bytes_before,
            done.bytes_after,
            done.files.len(),
            out.display()
        );
    }
    Ok(())
}

#[derive(clap::Args, Debug)]
struct EvaluateArgs {
    /// The policy folder.
    policy: PathBuf,
    /// Episodes to play (at each threshold, for a conditioned policy).
    #[arg(long, default_value_t = 20)]
    episodes: u32,
    /// Episode seeds are SEED, SEED+1, ...; recorded in the output.
    #[arg(long, default_value_t = 1_000_000)]
    seed: u64,
    /// Score a conditioned policy at this threshold only (default: each of the task's thresholds).
    #[arg(long)]
    cost_threshold: Option<f64>,
    /// Local simulator workers (default: one per core).
    #[arg(long)]
    workers: Option<u32>,
    /// Environments per worker session.
    #[arg(long, default_value_t = 10)]
    envs_per_session: u32,
    /// Sessions to spread the episodes over (default: as many as give every environment one episode, so each
    /// episode depends on its seed alone). Fewer sessions play several episodes per environment and create fewer
    /// environments: the leaderboard's layout, and the way to measure acting throughput (bench/acting.sh).
    #[arg(long)]
    sessions: Option<usize>,
    /// Worker binary (default: dsrl-sim-worker beside dsrl-admin).
    #[arg(long)]
    worker_binary: Option<PathBuf>,
    /// Print the result (with every episode) as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args, Debug)]
struct CollectArgs {
    /// Offline task id, e.g. OfflineMetadrive-easysparse-v0.
    #[arg(long)]
    task: String,
    /// Recipe file (default: data/recipes/<task>.toml under the current directory, the clone's root).
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
    /// Environments per worker session (MetaDrive: one process each, ~300 MB). IDM sweeps: where a session has
    /// one environment, or all its episodes are dealt at once, the driver plays whole episodes inside the worker
    /// (one round trip per episode, the same episodes as stepping); with `--settings-per-session` above 1, one
    /// environment per session is the fastest layout.
    #[arg(long, default_value_t = 4)]
    envs_per_session: u32,
    /// IDM sweeps: consecutive settings played in one session, whose environments switch the driver's settings on
    /// reset instead of being built again (MetaDrive builds one in ~4 s, about half an episode). 1, the default,
    /// is a fresh session per setting, as the committed MetaDrive starters were built; a larger block is faster
    /// and gives different (equally valid) episodes, since a reused environment does not replay a fresh one
    /// exactly. Recorded in the provenance; a resumed run replays unfinished blocks whole.
    #[arg(long, default_value_t = 1)]
    settings_per_session: u32,
    /// IDM sweeps: step every episode through the protocol (a round trip per step) even where the driver could
    /// play it whole in the worker. The same episodes, slower; kept to check that claim and to measure it.
    #[arg(long)]
    step_episodes: bool,
    /// Thin the result to at most N episodes, spread over the (reward, cost) plane like the trajectory buffer
    /// does (for starter datasets; a finished run's settings are reused, nothing is simulated again).
    #[arg(long)]
    max_episodes: Option<usize>,
    /// Output folder (default: the state folder).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write the output in the compact form: `next_observations` left out (null) wherever the next row of the
    /// episode starts from it, and `observations` one column per feature; less than half the size. Ingest
    /// gives back the canonical rows, so the version id is the canonical one. For committed starter files.
    #[arg(long)]
    compact: bool,
    /// With --compact: split the output into N files of whole episodes, `<name>.part-I-of-N.parquet`, each a
    /// dataset on its own and about 1/N of the rows. For a committed starter larger than one file may be (8 MB);
    /// the server's starter loader joins them back into one version, the canonical file's.
    #[arg(long, default_value_t = 1, requires = "compact", conflicts_with = "server")]
    parts: usize,
    /// Expert recipes with `warm_start`: the state folder of the finished build the expert starts from (default:
    /// `<state>/../<the warm start's task>`, its sibling under the same collect folder). Read only when the run
    /// starts; the provenance records the source's recipe, steps and the SHA-256 of its weights.
    #[arg(long)]
    warm_start: Option<PathBuf>,
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
}

fn cores() -> u32 {
    std::thread::available_parallelism()
        .map(|n| n.get() as u32)
        .unwrap_or(1)
}

async fn evaluate(args: EvaluateArgs) -> anyhow::Result<()> {
    use dsrl_evaluation::evaluator;
    use dsrl_policy::{Policy, checkpoint};
    let catalog = Catalog::embedded()?;
    let (config, tensors) = checkpoint::read(&args.policy)?;
    let task = catalog.get(&config.task)?.clone();
    evaluator::check_policy(&task, &config)?;
    let policy = Policy::load(&config, &tensors)?;
    // Where the episodes are played, and at which thresholds each play is scored: an unconditioned policy plays
    // once and is scored at every threshold; a per-threshold one at its own; a conditioned one plays at each.
    let plays: Vec<(f64, Vec<f64>)> = match (&config.conditioning, args.cost_threshold) {
        (checkpoint::Conditioning::PerThreshold { cost_threshold }, _) => {
            vec![(*cost_threshold, vec![*cost_threshold])]
        }
        (c, Some(k)) if c.is_conditioned() => vec![(k, vec![k])],
        (c, None) if c.is_conditioned() => task.cost_thresholds.iter().map(|&k| (k, vec![k])).collect(),
        _ => vec![(task.cost_thresholds[0], task.cost_thresholds.clone())],
    };
    let workers = args.workers.unwrap_or_else(cores).max(1);
    let pool = dsrl_evaluation::simulators::SimulatorPool::start(&SimulatorsConfig {
        local_workers: workers,
        worker_binary: args.worker_binary.clone(),
        ..SimulatorsConfig::default()
    });
    anyhow::ensure!(
        pool.wait_healthy(workers as usize, std::time::Duration::from_secs(180))
            .await,
        "simulator workers did not become healthy: {:?}",
        pool.workers()
    );
    let seed = args.seed;
    let seeds: Vec<u64> = (0..u64::from(args.episodes)).map(|i| seed + i).collect();
    let envs_per_session = args.envs_per_session.max(1) as usize;
    // By default one episode per environment (as many sessions as that takes): each episode depends on its seed
    // only. --sessions N lets environments play several.
    let sessions = args
        .sessions
        .unwrap_or_else(|| seeds.len().div_ceil(envs_per_session))
        .max(1);
    let started = std::time::Instant::now();
    let mut thresholds = Vec::new();
    let mut all_episodes = Vec::new();
    for (played_at, scored_at) in &plays {
        let scores = evaluator::play_episodes(
            &pool,
            &task,
            dsrl_evaluation::inference::PolicySource::Local(&policy),
            *played_at,
            &seeds,
            envs_per_session,
            sessions,
        )
        .await?;
        let n = scores.len().max(1) as f64;
        let reward = scores.iter().map(|s| s.reward_return).sum::<f64>() / n;
        let cost = scores.iter().map(|s| s.cost_return).sum::<f64>() / n;
        for &threshold in scored_at {
            let score = task.normalized_score(reward, cost, threshold);
            thresholds.push(serde_json::json!({
                "cost_threshold": threshold,
                "mean_reward_return": reward,
                "mean_cost_return": cost,
                "normalized_reward": score.reward,
                "normalized_cost": score.cost,
                "safe": score.cost <= 1.0,
            }));
        }
        all_episodes.push(scores);
    }
    // A single play's episodes at the top, else each threshold's beside it.
    let mut report = serde_json::json!({
        "task": task.id.as_str(),
        "policy": args.policy,
        "architecture": config.architecture.name(),
        "seeds": { "first": seed, "count": args.episodes },
        "layout": { "sessions": sessions, "envs_per_session": envs_per_session },
        "thresholds": thresholds,
        "wall_seconds": started.elapsed().as_secs_f64(),
    });
    if let [only] = &all_episodes[..] {
        report["episodes"] = serde_json::to_value(only)?;
        report["mean_reward_return"] = report["thresholds"][0]["mean_reward_return"].clone();
        report["mean_cost_return"] = report["thresholds"][0]["mean_cost_return"].clone();
    } else {
        for (t, episodes) in report["thresholds"]
            .as_array_mut()
            .expect("built above")
            .iter_mut()
            .zip(&all_episodes)
        {
            t["episodes"] = serde_json::to_value(episodes)?;
        }
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!("{}: {} episodes per play (seeds {seed}..)", task.id, args.episodes);
        for t in report["thresholds"].as_array().expect("built above") {
            println!(
                "  threshold {}: mean reward return {:.1}, mean cost return {:.1}, normalized reward {:.3}, \
                 normalized cost {:.3}{}",
                t["cost_threshold"],
                t["mean_reward_return"].as_f64().unwrap_or(f64::NAN),
                t["mean_cost_return"].as_f64().unwrap_or(f64::NAN),
                t["normalized_reward"].as_f64().unwrap_or(f64::NAN),
                t["normalized_cost"].as_f64().unwrap_or(f64::NAN),
                if t["safe"] == true { " (safe)" } else { "" }
            );
        }
    }
    Ok(())
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
    let CollectArgs {
        task,
        recipe,
        state,
        episodes_per_setting,
        budget_steps,
        workers,
        envs_per_session,
        settings_per_session,
        step_episodes,
        worker_binary,
        max_episodes,
        out,
        compact,
        parts,
        warm_start,
        server,
        token,
        tag,
        json,
    } = match Args::parse().command {
        Command::Evaluate(args) => return evaluate(args).await,
        Command::Compact(args) => return compact(args),
        Command::Collect(args) => args,
    };
    let catalog = Catalog::embedded()?;
    let recipe_path = match recipe {
        Some(path) => path,
        None => {
            let path = Recipe::default_path(&task);
            anyhow::ensure!(
                path.is_file(),
                "no recipe at {} under {}: run dsrl-admin from the root of the clone whose recipes it builds, \
                 or name one with --recipe",
                path.display(),
                std::env::current_dir()
                    .map(|d| d.display().to_string())
                    .unwrap_or_default()
            );
            path
        }
    };
    let recipe = Recipe::load(&recipe_path)?;
    anyhow::ensure!(
        recipe.task == task,
        "{} is the recipe of {}, not {task}",
        recipe_path.display(),
        recipe.task
    );
    let home = std::env::var_os("HOME").map(PathBuf::from).unwrap_or_default();
    let state_dir = state.unwrap_or_else(|| home.join(".dsrl/collect").join(&task));
    let run = Run {
        recipe,
        recipe_path,
        state_dir,
        episodes_per_setting,
        budget_steps,
        workers: workers.unwrap_or_else(cores).max(1),
        envs_per_session: envs_per_session.max(1),
        settings_per_session: settings_per_session.max(1),
        drive_episodes: !step_episodes,
        simulators: SimulatorsConfig {
            worker_binary,
            ..SimulatorsConfig::default()
        },
        progress: !json,
        max_episodes,
        out_dir: out,
        compact,
        parts: parts.max(1),
        warm_start_dir: warm_start,
    };
    let built = run.execute(&catalog).await?;
    let mut report = serde_json::json!({
        "task": task,
        "file": built.path,
        "files": built.files,
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
