//! `dsrl-train`: reference learners trained on the hosted datasets.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Parser, Subcommand, ValueEnum};
use dsrl_client::api::Client;
use dsrl_client::cache::{Cache, FetchOptions};
use dsrl_policy::checkpoint::Conditioning;
use dsrl_suite::Catalog;
use dsrl_train::bcql::{BcqlLearner, BcqlSettings};
use dsrl_train::{BcLearner, BcSettings, Demonstrations};
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Parser, Debug)]
#[command(
    version,
    about = "Trains reference policies in candle on dsrl datasets and writes them in the evaluator's checkpoint \
             format (policy.safetensors + policy.json), ready to score with `dsrl-admin evaluate`."
)]
struct Args {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Mode {
    /// Every episode of the dataset (one model).
    All,
    /// Only episodes whose cost return is at most the threshold (one model per threshold).
    Safe,
}

/// Where the training data comes from, how long to train and where the policies go: the same for every algorithm.
#[derive(clap::Args, Debug)]
struct DataArgs {
    /// Offline task id, e.g. OfflineBallRun-v0.
    #[arg(long)]
    task: String,
    /// A local dataset file (Parquet, canonical or compact) instead of fetching one.
    #[arg(long, conflicts_with = "server")]
    dataset: Option<PathBuf>,
    /// Fetch the dataset from this dsrl-server.
    #[arg(long, env = "DSRL_SERVER")]
    server: Option<String>,
    /// Version id or tag to fetch.
    #[arg(long, default_value = "latest")]
    version: String,
    /// A DSRL post-process filter for the fetched dataset, e.g. noise=0.05.
    #[arg(long)]
    filter: Option<String>,
    /// Thresholds to train per-threshold models for (default: the task's three benchmark thresholds).
    #[arg(long = "cost-threshold")]
    cost_thresholds: Vec<f64>,
    /// Gradient steps per model (OSRL: 100000; 200000 for MetaDrive). Recorded in policy.json.
    #[arg(long, default_value_t = 100_000)]
    steps: u64,
    /// Seed of initialization and batch sampling; recorded in policy.json.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output folder (default: ./policies/<task>).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Submit the trained entry to the leaderboard of --server under this name, with the user token in
    /// $DSRL_TOKEN; prints the submission id.
    #[arg(long, value_name = "NAME", requires = "server")]
    submit: Option<String>,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Behaviour cloning (OSRL's BC-All / BC-Safe): MLP actor [256, 256], MSE, Adam lr 1e-3, batch 512.
    ///
    /// The data comes from a local Parquet file (--dataset) or is fetched from a server (--server, with
    /// --version and --filter) into the dataset cache. Writes <out>/bc-all, or <out>/bc-safe/threshold-<K> per
    /// threshold: each folder is what `dsrl-client submit` takes (--submit does it here).
    Bc {
        #[arg(long, value_enum)]
        mode: Mode,
        #[command(flatten)]
        data: DataArgs,
    },
    /// BCQ-Lag (OSRL's bcql, spec 5.6): a VAE of the data's actions, a perturbation actor, double-ensemble reward
    /// and cost critics with target copies, a PID Lagrangian on the cost-Q (0.1, 0.003, 0.001); batch 512, lr 1e-3,
    /// reward scale 0.1. One model per threshold: <out>/bcql/threshold-<K>, each a `bcq_actor` checkpoint.
    Bcql {
        #[command(flatten)]
        data: DataArgs,
    },
}

/// The dataset named by `data`: read from its file, or fetched into the cache; with the fetched version id.
fn load_data(data: &DataArgs, task: &dsrl_suite::Task) -> anyhow::Result<(PathBuf, Option<String>, Demonstrations)> {
    let (path, dataset_version) = match (&data.dataset, &data.server) {
        (Some(path), _) => (path.clone(), None),
        (None, Some(server)) => {
            let fetched = tokio::runtime::Runtime::new()?.block_on(async {
                let client = Client::new(server)?;
                let options = FetchOptions {
                    hdf5: false,
                    filter: data.filter.clone(),
                    limit_rate: None,
                    progress: true,
                };
                Cache::new(Cache::default_root())
                    .fetch(&client, task.id.as_str(), &data.version, &options)
                    .await
            })?;
            (fetched.parquet_path, Some(fetched.version))
        }
        (None, None) => anyhow::bail!("name a dataset: --dataset FILE or --server URL"),
    };
    let demonstrations = Demonstrations::read(&path)?;
    anyhow::ensure!(
        (demonstrations.obs_dim, demonstrations.act_dim) == (task.obs_dim as usize, task.act_dim as usize),
        "{} holds observations of dim {} and actions of dim {}, but {} has {} and {}",
        path.display(),
        demonstrations.obs_dim,
        demonstrations.act_dim,
        task.id,
        task.obs_dim,
        task.act_dim
    );
    Ok((path, dataset_version, demonstrations))
}

fn progress(steps: u64) -> ProgressBar {
    let bar = ProgressBar::new(steps);
    bar.set_style(
        ProgressStyle::with_template("{msg} [{elapsed_precise}] {wide_bar} {pos}/{len} steps (eta {eta})")
            .expect("template"),
    );
    bar
}

/// Submits the folder `dir` (what `dsrl-client submit` takes) as `name`.
fn submit(server: &str, dir: &std::path::Path, task: &str, name: &str) -> anyhow::Result<()> {
    let token = std::env::var("DSRL_TOKEN").ok();
    anyhow::ensure!(token.is_some(), "--submit needs a user token in $DSRL_TOKEN");
    let submission = tokio::runtime::Runtime::new()?
        .block_on(async { Client::new(server)?.with_token(token).submit(dir, task, name).await })?;
    println!("submitted {} as {name}: submission {}", dir.display(), submission["id"]);
    Ok(())
}

/// BCQ-Lag, one model per threshold.
fn train_bcql(data: DataArgs) -> anyhow::Result<()> {
    let catalog = Catalog::embedded()?;
    let task = catalog.get(&data.task)?.clone();
    let (path, dataset_version, demonstrations) = load_data(&data, &task)?;
    let out = data
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("policies").join(task.id.as_str()));
    let thresholds = if data.cost_thresholds.is_empty() {
        task.cost_thresholds.clone()
    } else {
        data.cost_thresholds.clone()
    };
    let settings = BcqlSettings {
        steps: data.steps,
        seed: data.seed,
        ..BcqlSettings::default()
    };
    for kappa in thresholds {
        let name = format!("bcql/threshold-{kappa}");
        let episode_len = task.max_episode_steps as usize;
        let mut learner = BcqlLearner::new(settings.clone(), &demonstrations, kappa, episode_len)?;
        let bar = progress(data.steps);
        let started = std::time::Instant::now();
        let mut stats = Default::default();
        for step in 0..data.steps {
            stats = learner.step()?;
            if step % 100 == 0 {
                bar.set_position(step);
                bar.set_message(format!(
                    "{name} critic {:.4} λ {:.3}",
                    stats.critic_loss, stats.lagrangian
                ));
            }
        }
        bar.finish_and_clear();
        let seconds = started.elapsed().as_secs_f64();
        let stats: dsrl_train::bcql::BcqlStats = stats;
        let training = serde_json::json!({
            "algorithm": "bcql",
            "dataset": path.file_name().map(|n| n.to_string_lossy().into_owned()),
            "dataset_version": dataset_version,
            "filter": data.filter,
            "transitions": demonstrations.rows(),
            "steps": data.steps,
            "batch_size": settings.batch_size,
            "settings": format!("{settings:?}"),
            "qc_threshold": learner.qc_threshold(),
            "seed": data.seed,
            "final": {"vae": stats.vae_loss, "critic": stats.critic_loss, "cost_critic": stats.cost_critic_loss,
                      "actor": stats.actor_loss, "lagrangian": stats.lagrangian},
            "seconds": seconds,
        });
        let dir = out.join(&name);
        learner
            .write(&dir, task.id.as_str(), kappa, training)
            .with_context(|| format!("writing {}", dir.display()))?;
        println!(
            "{name}: {} steps in {seconds:.0} s, final λ {:.3} -> {}",
            data.steps,
            stats.lagrangian,
            dir.display()
        );
    }
    if let (Some(name), Some(server)) = (&data.submit, &data.server) {
        submit(server, &out.join("bcql"), task.id.as_str(), name)?;
    }
    Ok(())
}

fn main() -> anyhow::Result<()> {
    // SAFETY: first thing in main, before the runtime or any other thread exists.
    unsafe { dsrl_policy::pin_candle_threads() };
    let (mode, data) = match Args::parse().command {
        Command::Bc { mode, data } => (mode, data),
        Command::Bcql { data } => return train_bcql(data),
    };
    let DataArgs {
        task,
        cost_thresholds,
        steps,
        seed,
        out,
        submit: submit_as,
        ..
    } = &data;
    let (cost_thresholds, steps, seed) = (cost_thresholds.clone(), *steps, *seed);
    let catalog = Catalog::embedded()?;
    let task = catalog.get(task)?.clone();
    let (path, dataset_version, data_read) = load_data(&data, &task)?;
    let server = data.server.clone();
    let data = data_read;
    let out = out
        .clone()
        .unwrap_or_else(|| PathBuf::from("policies").join(task.id.as_str()));
    let settings = BcSettings {
        steps,
        seed,
        ..BcSettings::default()
    };
    let models: Vec<Option<f64>> = match mode {
        Mode::All => vec![None],
        Mode::Safe if cost_thresholds.is_empty() => task.cost_thresholds.iter().copied().map(Some).collect(),
        Mode::Safe => cost_thresholds.into_iter().map(Some).collect(),
    };
    for threshold in models {
        let (obs, act, kept) = data.select(threshold);
        let name = match threshold {
            None => "bc-all".to_owned(),
            Some(k) => format!("bc-safe/threshold-{k}"),
        };
        anyhow::ensure!(
            kept > 0,
            "{name}: no episode of the dataset has a cost return of at most {}",
            threshold.unwrap_or_default()
        );
        let mut learner = BcLearner::new(&settings, &obs, &act, data.obs_dim, data.act_dim)?;
        let bar = progress(steps);
        let started = std::time::Instant::now();
        let mut loss = f64::NAN;
        for step in 0..steps {
            loss = learner.step()?;
            if step % 500 == 0 {
                bar.set_position(step);
                bar.set_message(format!("{name} mse {loss:.5}"));
            }
        }
        bar.finish_and_clear();
        let seconds = started.elapsed().as_secs_f64();
        let dir = out.join(&name);
        let conditioning = match threshold {
            None => Conditioning::Unconditioned,
            Some(cost_threshold) => Conditioning::PerThreshold { cost_threshold },
        };
        let training = serde_json::json!({
            "algorithm": if threshold.is_some() { "bc-safe" } else { "bc-all" },
            "dataset": path.file_name().map(|n| n.to_string_lossy().into_owned()),
            "dataset_version": dataset_version,
            "episodes": kept,
            "transitions": obs.len() / data.obs_dim,
            "steps": steps,
            "batch_size": settings.batch_size,
            "lr": settings.lr,
            "seed": seed,
            "final_mse": loss,
            "seconds": seconds,
        });
        learner
            .write(&dir, task.id.as_str(), &settings.hidden_sizes, conditioning, training)
            .with_context(|| format!("writing {}", dir.display()))?;
        println!(
            "{name}: {kept} episodes, {steps} steps in {seconds:.0} s, final MSE {loss:.5} -> {}",
            dir.display()
        );
    }
    if let (Some(name), Some(server)) = (submit_as, server) {
        let dir = out.join(if mode == Mode::All { "bc-all" } else { "bc-safe" });
        submit(&server, &dir, task.id.as_str(), name)?;
    }
    Ok(())
}
