//! `dsrl-train`: reference learners trained on the hosted datasets.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Parser, Subcommand, ValueEnum};
use dsrl_client::api::Client;
use dsrl_client::cache::{Cache, FetchOptions};
use dsrl_policy::checkpoint::Conditioning;
use dsrl_suite::Catalog;
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

#[derive(Subcommand, Debug)]
enum Command {
    /// Behaviour cloning (OSRL's BC-All / BC-Safe): MLP actor [256, 256], MSE, Adam lr 1e-3, batch 512.
    ///
    /// The data comes from a local Parquet file (--dataset) or is fetched from a server (--server, with
    /// --version and --filter) into the dataset cache. Writes <out>/bc-all, or <out>/bc-safe/threshold-<K> per
    /// threshold: each folder is what `dsrl-client submit` takes (--submit does it here).
    Bc {
        /// Offline task id, e.g. OfflineBallRun-v0.
        #[arg(long)]
        task: String,
        #[arg(long, value_enum)]
        mode: Mode,
        /// A local dataset file (Parquet) instead of fetching one.
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
        /// BC-Safe thresholds (default: the task's three benchmark thresholds).
        #[arg(long = "cost-threshold")]
        cost_thresholds: Vec<f64>,
        /// Gradient steps per model (OSRL: 100000; 200000 for MetaDrive).
        #[arg(long, default_value_t = 100_000)]
        steps: u64,
        /// Seed of initialization and batch sampling; recorded in policy.json.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Output folder (default: ./policies/<task>).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Submit the trained entry to the leaderboard of --server under this name (BC-All / BC-Safe are the
        /// paper's), with the user token in $DSRL_TOKEN; prints the submission id.
        #[arg(long, value_name = "NAME", requires = "server")]
        submit: Option<String>,
    },
}

fn main() -> anyhow::Result<()> {
    // SAFETY: first thing in main, before the runtime or any other thread exists.
    unsafe { dsrl_policy::pin_candle_threads() };
    let Command::Bc {
        task,
        mode,
        dataset,
        server,
        version,
        filter,
        cost_thresholds,
        steps,
        seed,
        out,
        submit,
    } = Args::parse().command;
    let catalog = Catalog::embedded()?;
    let task = catalog.get(&task)?.clone();
    let (path, dataset_version) = match (dataset, &server) {
        (Some(path), _) => (path, None),
        (None, Some(server)) => {
            let fetched = tokio::runtime::Runtime::new()?.block_on(async {
                let client = Client::new(server)?;
                let options = FetchOptions {
                    hdf5: false,
                    filter,
                    limit_rate: None,
                    progress: true,
                };
                Cache::new(Cache::default_root())
                    .fetch(&client, task.id.as_str(), &version, &options)
                    .await
            })?;
            (fetched.parquet_path, Some(fetched.version))
        }
        (None, None) => anyhow::bail!("name a dataset: --dataset FILE or --server URL"),
    };
    let data = Demonstrations::read(&path)?;
    anyhow::ensure!(
        (data.obs_dim, data.act_dim) == (task.obs_dim as usize, task.act_dim as usize),
        "{} holds observations of dim {} and actions of dim {}, but {} has {} and {}",
        path.display(),
        data.obs_dim,
        data.act_dim,
        task.id,
        task.obs_dim,
        task.act_dim
    );
    let out = out.unwrap_or_else(|| PathBuf::from("policies").join(task.id.as_str()));
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
        let bar = ProgressBar::new(steps);
        bar.set_style(
            ProgressStyle::with_template("{msg} [{elapsed_precise}] {wide_bar} {pos}/{len} steps (eta {eta})")
                .expect("template"),
        );
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
    if let (Some(name), Some(server)) = (submit, server) {
        let dir = out.join(if mode == Mode::All { "bc-all" } else { "bc-safe" });
        let token = std::env::var("DSRL_TOKEN").ok();
        anyhow::ensure!(token.is_some(), "--submit needs a user token in $DSRL_TOKEN");
        let submission = tokio::runtime::Runtime::new()?.block_on(async {
            Client::new(&server)?
                .with_token(token)
                .submit(&dir, task.id.as_str(), &name)
                .await
        })?;
        println!("submitted {} as {name}: submission {}", dir.display(), submission["id"]);
    }
    Ok(())
}
