//! `dsrl-train`: reference learners trained on the hosted datasets.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Parser, Subcommand, ValueEnum};
use dsrl_client::api::Client;
use dsrl_client::cache::{Cache, FetchOptions};
use dsrl_client::out;
use dsrl_policy::Device;
use dsrl_policy::checkpoint::Conditioning;
use dsrl_suite::Catalog;
use dsrl_train::bcql::{BcqlLearner, BcqlSettings};
use dsrl_train::bearl::{BearlLearner, BearlSettings};
use dsrl_train::caps::{CapsLearner, CapsSettings};
use dsrl_train::cdt::{CdtLearner, CdtSettings, return_targets, task_augmentation};
use dsrl_train::coptidice::{CoptidiceLearner, CoptidiceSettings};
use dsrl_train::cpq::{CpqLearner, CpqSettings};
use dsrl_train::fisor::{FisorLearner, FisorSettings};
use dsrl_train::lspc::{LspcLearner, LspcSettings};
use dsrl_train::offline::{EveryThresholdLearner, ThresholdLearner};
use dsrl_train::{BcLearner, BcSettings, Demonstrations};
use indicatif::{ProgressBar, ProgressStyle};

/// The git commit this binary was built from (`-modified` when the learners' sources differed from it), recorded
/// in every model's training record.
const CODE_COMMIT: &str = env!("DSRL_BUILD_COMMIT");

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
    /// A local dataset file (Parquet, canonical or compact, or DSRL HDF5) instead of fetching one. It wins over
    /// --server / $DSRL_SERVER for the data; the server then only receives the entry of --submit. Its version id
    /// (the sha256 of its canonical form, as the server would host it) is recorded like a fetched one.
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Fetch the dataset from this dsrl-server (unless --dataset names a file), and submit to it with --submit.
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
    /// Batch size instead of OSRL's for the algorithm (512; CDT 2048), e.g. to try a pipeline on a small machine;
    /// recorded in policy.json.
    #[arg(long)]
    batch_size: Option<usize>,
    /// Seed of initialization and batch sampling; recorded in policy.json.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Where to train: cpu, or cuda / cuda:N (the N-th GPU) in a binary built with the `cuda` feature
    /// (scripts/build-cuda.sh), for every method. Networks are initialised on the CPU from the seed and moved;
    /// batches are drawn on the host from the same seeded generator, so a run's random choices do not depend on the
    /// device. Checkpoints are float32 on the CPU either way; the device is recorded in policy.json.
    #[arg(long, default_value = "cpu")]
    device: String,
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
    /// CDT (OSRL's cdt, spec 5.4): the Constrained Decision Transformer (embedding 128, 3 blocks of 8 heads,
    /// context 10, dropout 0.1; batch 2048, AdamW lr 1e-4 with weight decay 1e-4, warm-up 500 steps, gradient
    /// clip 0.25). Trained once; <out>/cdt is scored at each benchmark threshold from OSRL's (reward, cost) target
    /// for it (data/cdt_targets.csv), with OSRL's return augmentation (20% relabelled copies). OSRL trains
    /// 100000 steps (200000 MetaDrive).
    Cdt {
        #[command(flatten)]
        data: DataArgs,
    },
    /// BEAR-Lag (OSRL's bearl, spec 5.7): a squashed Gaussian actor held to the data by an MMD constraint (Gaussian
    /// kernel, σ 50, target 0.05) against a VAE of the actions, double-ensemble critics, a PID Lagrangian on the
    /// cost-Q; batch 512, lr 1e-3. OSRL trains 300000 steps (200000 MetaDrive). One model per threshold:
    /// <out>/bearl/threshold-<K>, each a `squashed_gaussian_mlp` played at tanh(mean).
    Bearl {
        #[command(flatten)]
        data: DataArgs,
    },
    /// CPQ (OSRL's cpq, spec 5.8): constraint-penalized Q-learning — the reward backup is cut where the cost-Q of
    /// the next action passes the threshold, and the actor maximises reward-Q only where its cost-Q is within it;
    /// a VAE flags out-of-distribution actions. Actor lr 1e-4, critics and VAE 1e-3, batch 512. One model per
    /// threshold: <out>/cpq/threshold-<K>.
    Cpq {
        #[command(flatten)]
        data: DataArgs,
    },
    /// COptiDICE (OSRL's coptidice, spec 5.8): stationary-distribution correction with the soft-χ² divergence
    /// (α 0.5), a cost upper bound (ε 0.01), a Lagrange multiplier, and a policy extracted by weighted behaviour
    /// cloning; lrs 1e-4, batch 512. One model per threshold: <out>/coptidice/threshold-<K>.
    Coptidice {
        #[command(flatten)]
        data: DataArgs,
    },
    /// CAPS (Chemingui et al., AAAI 2025; its IQL variant): beyond the paper's baselines. Five policy heads on a
    /// shared trunk, each regressed on the data's actions with its own mix of reward and cost advantages, and
    /// reward and cost critics learned by implicit Q-learning (hidden [512, 512], lrs 3e-4, batch 512, β 3,
    /// expectile 0.7). Trained once; <out>/caps is scored at every threshold, given as the episode's cost budget:
    /// at each step it plays the head with the highest predicted reward among those whose predicted cost fits what
    /// is left of the budget. CAPS trains 100000 steps.
    Caps {
        #[command(flatten)]
        data: DataArgs,
    },
    /// FISOR (Zheng et al., ICLR 2024): beyond the paper's baselines. A hard constraint as a feasibility value
    /// (reachability critics on costs recoded +25/−1, a reversed expectile), and a diffusion actor (5 denoising
    /// steps, residual noise network 3×256 with LayerNorm and dropout 0.1) trained by noise regression weighted
    /// towards feasibility where the state is infeasible and towards reward advantage where it is feasible; batch
    /// 2×1024 for the actor, 256 for the critics, lrs 3e-4 (the actor's on a cosine over 3M actor updates), EMA
    /// actor τ 0.001. Trained once; <out>/fisor is scored at every threshold: 16 candidate actions per step, the one
    /// with the lowest feasibility value played. FISOR trains 1000000 steps.
    Fisor {
        #[command(flatten)]
        data: DataArgs,
    },
    /// LSPC (Koirala & Fleming, ICLR 2025): beyond the paper's baselines. A conditional VAE (latent 32) learns the
    /// data's actions weighted towards safe ones (by a cost advantage from IQL-style cost critics), and a safety
    /// encoder learns by advantage-weighted regression which latent the decoder should play for reward (β 2,
    /// expectile 0.7, hidden 256, lr 3e-4, batch 1024; the latent bounded at 0.6 on Bullet tasks but AntRun, 0.25
    /// elsewhere). Trained once; <out>/lspc is scored at every threshold, the encoder's latent drawn per step from
    /// the episode's seed (LSPC-O). LSPC trains 1000000 steps.
    Lspc {
        #[command(flatten)]
        data: DataArgs,
    },
    /// One update from given weights, batch and seed, with its losses, gradients and new weights written out
    /// (tests/parity/osrl_step_check.py holds them to OSRL's PyTorch code).
    #[command(hide = true)]
    Parity { dir: PathBuf },
    /// Writes a scored model as a line of the reference results file (data/reference/results.jsonl): its budget,
    /// seed, dataset version and code commit from the models' policy.json, its checkpoint digest, protocol version
    /// and every episode from the leaderboard's JSON for its submission (`dsrl-client status ID --json`). Replaces
    /// the entry of the same task, method and seed. `dsrl-admin reference` runs it after each scoring. The
    /// model's checkpoints must have the digest the submission scored.
    ///
    /// With --reproduce instead of --submission: the model was trained again from scratch, and the entry already
    /// in the file takes its training record (code commit, seconds) when its checkpoints have the digest the entry
    /// was scored with (so the networks are the ones scored); otherwise it fails and changes nothing
    /// (`dsrl-admin reference --reproduce`).
    ReferenceEntry {
        /// The model folder that was submitted (e.g. policies/<task>/seed-0/bc-safe), or trained again.
        #[arg(long)]
        model: PathBuf,
        /// The submission's JSON, as the server answered it once finished.
        #[arg(long, required_unless_present = "reproduce", conflicts_with = "reproduce")]
        submission: Option<PathBuf>,
        /// Re-record the existing entry for a model trained again, if its checkpoints are the ones scored.
        #[arg(long)]
        reproduce: bool,
        /// The method's name as the paper writes it: BC-All, BC-Safe, CDT, BCQ-Lag, BEAR-Lag, CPQ, COptiDICE, CAPS.
        #[arg(long)]
        method: String,
        /// The results file to update.
        #[arg(long, default_value = "data/reference/results.jsonl")]
        results: PathBuf,
    },
}

/// The version id a local dataset file would be hosted under: the sha256 of its canonical form, written to a
/// temporary file while the file is validated against the task (an invalid file is refused here, as ingest would).
fn local_version(path: &std::path::Path, task: &dsrl_suite::Task) -> anyhow::Result<String> {
    let scratch = tempfile::NamedTempFile::new().context("creating a temporary file for the canonical form")?;
    let (_, converted) = dsrl_suite::convert::import_file(
        path,
        task,
        dsrl_suite::catalog::ObservationSpace::Simulator,
        scratch.path(),
    )
    .with_context(|| format!("reading {} as a dataset of {}", path.display(), task.id))?;
    Ok(converted.version.as_str().to_owned())
}

/// The dataset named by `data`: read from its file, or fetched into the cache; with its version id.
fn load_data(data: &DataArgs, task: &dsrl_suite::Task) -> anyhow::Result<(PathBuf, Option<String>, Demonstrations)> {
    let (path, dataset_version) = match (&data.dataset, &data.server) {
        (Some(path), _) => (path.clone(), Some(local_version(path, task)?)),
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
            (fetched.path, Some(fetched.version))
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

/// What every algorithm starts from: the task, its training data and the output folder the data options name.
struct Prepared {
    task: dsrl_suite::Task,
    source: Source,
    demonstrations: Demonstrations,
    out: PathBuf,
    device: Device,
}

/// Which data a model was trained on, as its training record names it.
struct Source {
    path: PathBuf,
    dataset_version: Option<String>,
    transitions: usize,
    /// The device trained on (`cpu`, `cuda:0`, ...).
    device: String,
}

fn prepare(data: &DataArgs) -> anyhow::Result<Prepared> {
    let device = dsrl_train::training_device(&data.device)?;
    let catalog = Catalog::embedded()?;
    let task = catalog.get(&data.task)?.clone();
    let (path, dataset_version, demonstrations) = load_data(data, &task)?;
    let out = data
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("policies").join(task.id.as_str()));
    let source = Source {
        path,
        dataset_version,
        transitions: demonstrations.rows(),
        device: dsrl_train::device_name(&device),
    };
    Ok(Prepared {
        task,
        source,
        demonstrations,
        out,
        device,
    })
}

/// What a training loop leaves: the last step's figures and its timing.
struct Trained {
    figures: Vec<(&'static str, f64)>,
    seconds: f64,
    /// CPU seconds of the training thread (user + system) over the same steps: the compute, whatever else shares
    /// the machine.
    cpu_seconds: f64,
    /// The first step alone (page faults, first allocations): benchmarks leave it out as PyTorch's warm-up.
    first_step_seconds: Option<f64>,
}

impl Trained {
    /// The last figures as the training record's `final`.
    fn last(&self) -> serde_json::Map<String, serde_json::Value> {
        self.figures
            .iter()
            .map(|(n, v)| ((*n).to_owned(), serde_json::json!(v)))
            .collect()
    }

    /// `name value, ...` for the closing line.
    fn summary(&self) -> String {
        let shown: Vec<String> = self.figures.iter().map(|(n, v)| format!("{n} {v:.4}")).collect();
        shown.join(", ")
    }

    /// The closing line of a trained model written to `dir`.
    fn report(&self, name: &str, steps: u64, dir: &std::path::Path) {
        out!(
            "{name}: {steps} steps in {:.0} s ({}) -> {}",
            self.seconds,
            self.summary(),
            dir.display()
        );
    }
}

impl Source {
    /// The training record every algorithm writes (what was trained on, for how long, with which seed, how it
    /// ended), with the algorithm's own fields in `extra`.
    fn training_record(
        &self,
        algorithm: &str,
        data: &DataArgs,
        batch_size: usize,
        trained: &Trained,
        extra: serde_json::Value,
    ) -> serde_json::Value {
        let mut record = serde_json::json!({
            "algorithm": algorithm,
            "dataset": self.path.file_name().map(|n| n.to_string_lossy().into_owned()),
            "dataset_version": self.dataset_version,
            "filter": data.filter,
            "transitions": self.transitions,
            "steps": data.steps,
            "batch_size": batch_size,
            "seed": data.seed,
            "code_commit": CODE_COMMIT,
            "device": self.device,
            "cpu": cpu_model(),
            "final": trained.last(),
            "seconds": trained.seconds,
            "cpu_seconds": trained.cpu_seconds,
            "first_step_seconds": trained.first_step_seconds,
        });
        if let (Some(record), serde_json::Value::Object(extra)) = (record.as_object_mut(), extra) {
            record.extend(extra);
        }
        record
    }
}

/// CPU seconds (user + system) this thread has used; training runs on one thread (`pin_candle_threads`).
fn thread_cpu_seconds() -> f64 {
    let mut t = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes into the valid timespec it is given.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) };
    if rc == 0 {
        t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9
    } else {
        f64::NAN
    }
}

/// The CPU this process trains on, as training records name it: its model name, whether it has AVX-512, and the
/// matrix kernels candle runs on it (which decide the checkpoint's bits; before gemm's AVX-512 kernels were turned
/// off, records said only "AVX-512: yes", and those ran them); None where `/proc/cpuinfo` does not say.
fn cpu_model() -> Option<String> {
    let info = std::fs::read_to_string("/proc/cpuinfo").ok()?;
    let field = |key: &str| {
        info.lines()
            .find(|l| l.split(':').next().is_some_and(|k| k.trim() == key))
            .and_then(|l| l.split_once(':'))
            .map(|(_, v)| v.trim())
    };
    let avx512 = field("flags").is_some_and(|f| f.split_whitespace().any(|f| f == "avx512f"));
    Some(format!(
        "{}, AVX-512: {}, {} kernels",
        field("model name")?,
        if avx512 { "yes" } else { "no" },
        dsrl_policy::matrix_kernels()
    ))
}

/// Runs `step` `steps` times under a progress bar labelled `label` (its first `shown` figures every `every` steps).
fn train_loop(
    steps: u64,
    label: &str,
    every: u64,
    shown: usize,
    mut step: impl FnMut() -> anyhow::Result<Vec<(&'static str, f64)>>,
) -> anyhow::Result<Trained> {
    let bar = progress(steps);
    let started = std::time::Instant::now();
    let cpu_started = thread_cpu_seconds();
    let mut figures = Vec::new();
    let mut first_step_seconds = None;
    for i in 0..steps {
        figures = step()?;
        first_step_seconds.get_or_insert_with(|| started.elapsed().as_secs_f64());
        if i % every == 0 {
            bar.set_position(i);
            let head: Vec<String> = figures.iter().take(shown).map(|(n, v)| format!("{n} {v:.4}")).collect();
            bar.set_message(format!("{label} {}", head.join(" ")));
        }
    }
    bar.finish_and_clear();
    Ok(Trained {
        figures,
        seconds: started.elapsed().as_secs_f64(),
        cpu_seconds: thread_cpu_seconds() - cpu_started,
        first_step_seconds,
    })
}

/// Submits the folder `dir` (what `dsrl-client submit` takes) as `name`.
fn submit(server: &str, dir: &std::path::Path, task: &str, name: &str) -> anyhow::Result<()> {
    let token = std::env::var("DSRL_TOKEN").ok();
    anyhow::ensure!(token.is_some(), "--submit needs a user token in $DSRL_TOKEN");
    let submission = tokio::runtime::Runtime::new()?
        .block_on(async { Client::new(server)?.with_token(token).submit(dir, task, name).await })?;
    out!("submitted {} as {name}: submission {}", dir.display(), submission["id"]);
    Ok(())
}

/// How to build a per-threshold algorithm's learner for one threshold (`kappa`, the task's episode length, the
/// seed, a batch size other than OSRL's, the device it trains on).
type MakeLearner =
    dyn Fn(&Demonstrations, f64, usize, u64, Option<usize>, &Device) -> anyhow::Result<Box<dyn ThresholdLearner>>;

/// A per-threshold method's settings as a run sets them: OSRL's defaults (`Default`) with the run's seed, its batch
/// size when one was given, and its steps where the method's schedule depends on them.
trait RunSettings: Default {
    fn for_run(self, seed: u64, batch_size: Option<usize>, steps: u64) -> Self;
}

impl RunSettings for BcqlSettings {
    fn for_run(self, seed: u64, batch_size: Option<usize>, steps: u64) -> Self {
        let batch_size = batch_size.unwrap_or(self.batch_size);
        BcqlSettings {
            seed,
            batch_size,
            steps,
            ..self
        }
    }
}

/// The methods whose settings a run sets only by seed and batch size.
macro_rules! seed_and_batch_size {
    ($($settings:ident),*) => {$(
        impl RunSettings for $settings {
            fn for_run(self, seed: u64, batch_size: Option<usize>, _steps: u64) -> Self {
                let batch_size = batch_size.unwrap_or(self.batch_size);
                $settings { seed, batch_size, ..self }
            }
        }
    )*};
}
seed_and_batch_size!(BearlSettings, CpqSettings, CoptidiceSettings);

/// The command of a per-threshold method: its learner built by `on_device` from the run's settings, one per
/// threshold.
fn per_threshold<S: RunSettings + 'static, L: ThresholdLearner + 'static>(
    algorithm: &str,
    data: DataArgs,
    on_device: fn(S, &Demonstrations, f64, usize, &Device) -> anyhow::Result<L>,
) -> anyhow::Result<()> {
    let steps = data.steps;
    train_per_threshold(algorithm, data, &move |d, kappa, len, seed, batch, device| {
        let settings = S::default().for_run(seed, batch, steps);
        Ok(Box::new(on_device(settings, d, kappa, len, device)?))
    })
}

/// Trains one model per threshold with `make`, writes `<out>/<algorithm>/threshold-<K>` and optionally submits.
fn train_per_threshold(algorithm: &str, data: DataArgs, make: &MakeLearner) -> anyhow::Result<()> {
    let Prepared {
        task,
        source,
        demonstrations,
        out,
        device,
    } = prepare(&data)?;
    let thresholds = if data.cost_thresholds.is_empty() {
        task.cost_thresholds.clone()
    } else {
        data.cost_thresholds.clone()
    };
    let episode_len = task.max_episode_steps as usize;
    for kappa in thresholds {
        let name = format!("{algorithm}/threshold-{kappa}");
        let mut learner = make(&demonstrations, kappa, episode_len, data.seed, data.batch_size, &device)?;
        let trained = train_loop(data.steps, &name, 100, 4, || learner.step())?;
        let extra = serde_json::json!({ "settings": learner.settings(), "qc_threshold": learner.qc_threshold() });
        let training = source.training_record(algorithm, &data, learner.batch_size(), &trained, extra);
        let dir = out.join(&name);
        learner
            .write(&dir, task.id.as_str(), kappa, training)
            .with_context(|| format!("writing {}", dir.display()))?;
        trained.report(&name, data.steps, &dir);
    }
    if let (Some(name), Some(server)) = (&data.submit, &data.server) {
        submit(server, &out.join(algorithm), task.id.as_str(), name)?;
    }
    Ok(())
}

/// What a method trained once and scored at every threshold (CAPS, FISOR, LSPC) hands [`train_one_model`].
struct OneModel<'a> {
    /// The model's folder name under the output folder, and the progress label.
    name: &'a str,
    batch_size: usize,
    settings: String,
    departures: &'a str,
}

/// Trains a model that serves every threshold, writes `<out>/<name>`, reports, and submits when asked.
fn train_one_model(
    model: OneModel,
    data: &DataArgs,
    prepared: Prepared,
    learner: &mut dyn EveryThresholdLearner,
) -> anyhow::Result<()> {
    let Prepared { task, source, out, .. } = prepared;
    let trained = train_loop(data.steps, model.name, 10, 5, || learner.step())?;
    let extra = serde_json::json!({"settings": model.settings, "departures": model.departures});
    let training = source.training_record(model.name, data, model.batch_size, &trained, extra);
    let dir = out.join(model.name);
    learner
        .write(&dir, task.id.as_str(), training)
        .with_context(|| format!("writing {}", dir.display()))?;
    trained.report(model.name, data.steps, &dir);
    if let (Some(name), Some(server)) = (&data.submit, &data.server) {
        submit(server, &dir, task.id.as_str(), name)?;
    }
    Ok(())
}

/// The check of a method that is trained once for every threshold.
fn no_thresholds(data: &DataArgs, method: &str, how: &str) -> anyhow::Result<()> {
    anyhow::ensure!(
        data.cost_thresholds.is_empty(),
        "{method} is trained once and scored at every benchmark threshold{how}; drop --cost-threshold"
    );
    Ok(())
}

fn train_caps(data: DataArgs) -> anyhow::Result<()> {
    no_thresholds(&data, "CAPS", " as a cost budget")?;
    let prepared = prepare(&data)?;
    let default = CapsSettings::default();
    let settings = CapsSettings {
        seed: data.seed,
        batch_size: data.batch_size.unwrap_or(default.batch_size),
        ..default
    };
    let horizon = prepared.task.max_episode_steps as usize;
    let mut learner = CapsLearner::on_device(settings.clone(), &prepared.demonstrations, horizon, &prepared.device)?;
    let model = OneModel {
        name: "caps",
        batch_size: settings.batch_size,
        settings: format!("{settings:?}"),
        departures: "batches drawn by the seeded generator; every other choice as CAPS's capsiql.py",
    };
    train_one_model(model, &data, prepared, &mut learner)
}

fn train_fisor(data: DataArgs) -> anyhow::Result<()> {
    no_thresholds(&data, "FISOR", "")?;
    if let Some(b) = data.batch_size {
        anyhow::ensure!(
            b >= 8 && b.is_multiple_of(2),
            "FISOR's --batch-size is what a step draws, split into two actor halves with an eighth for the critics: \
             give an even number of at least 8"
        );
    }
    let prepared = prepare(&data)?;
    let default = FisorSettings::default();
    let settings = FisorSettings {
        seed: data.seed,
        // --batch-size is what one step draws (FISOR's 2048): the actor trains on its two halves, the critics on
        // an eighth of it (FISOR's 256).
        actor_batch: data.batch_size.map_or(default.actor_batch, |b| (b / 2).max(1)),
        critic_batch: data.batch_size.map_or(default.critic_batch, |b| (b / 8).max(1)),
        reward_scale: FisorSettings::reward_scale_for(&prepared.task),
        ..default
    };
    let mut learner = FisorLearner::on_device(settings.clone(), &prepared.demonstrations, &prepared.device)?;
    let model = OneModel {
        name: "fisor",
        batch_size: 2 * settings.actor_batch,
        settings: format!("{settings:?}"),
        departures: "batches, step indices, noise and dropout drawn by the seeded generator (JAX's cannot be matched); \
                     critics start from PyTorch's default initialisation, not xavier-uniform",
    };
    train_one_model(model, &data, prepared, &mut learner)
}

fn train_lspc(data: DataArgs) -> anyhow::Result<()> {
    no_thresholds(&data, "LSPC", "")?;
    let prepared = prepare(&data)?;
    let default = LspcSettings::for_task(&prepared.task);
    let settings = LspcSettings {
        seed: data.seed,
        batch_size: data.batch_size.unwrap_or(default.batch_size),
        ..default
    };
    let mut learner = LspcLearner::on_device(settings.clone(), &prepared.demonstrations, &prepared.device)?;
    let model = OneModel {
        name: "lspc",
        batch_size: settings.batch_size,
        settings: format!("{settings:?}"),
        departures: "batches and latent draws from the seeded generator; at evaluation the encoder's latent is drawn \
                     from the episode's seed",
    };
    train_one_model(model, &data, prepared, &mut learner)
}

/// CDT: one model for every threshold.
fn train_cdt(data: DataArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        data.cost_thresholds.is_empty(),
        "CDT is trained once and scored at the task's benchmark thresholds from OSRL's targets; drop --cost-threshold"
    );
    let Prepared {
        task,
        source,
        demonstrations,
        out,
        device,
    } = prepare(&data)?;
    let targets = return_targets(task.id.as_str())?;
    let default = CdtSettings::default();
    let settings = CdtSettings {
        seed: data.seed,
        batch_size: data.batch_size.unwrap_or(default.batch_size),
        ..default
    };
    let episodes = demonstrations.episodes.len();
    let augmentation = task_augmentation(task.id.as_str())?;
    let mut learner = CdtLearner::on_device(
        settings.clone(),
        demonstrations,
        task.max_episode_steps as usize,
        Some(&augmentation),
        &device,
    )?;
    let trained = train_loop(data.steps, "cdt", 10, 3, || learner.step())?;
    let extra = serde_json::json!({
        "episodes": episodes,
        "settings": format!("{settings:?}"),
        "sampling": learner.sampling,
        "augmentation": format!("{augmentation:?}"),
        "augmented_trajectories": learner.augmented,
        "departures": "augmentation draws from the seeded generator, not Python's and NumPy's; the state head is not decayed",
    });
    let training = source.training_record("cdt", &data, settings.batch_size, &trained, extra);
    let dir = out.join("cdt");
    learner
        .write(&dir, task.id.as_str(), &task.cost_thresholds, &targets, training)
        .with_context(|| format!("writing {}", dir.display()))?;
    trained.report("cdt", data.steps, &dir);
    if let (Some(name), Some(server)) = (&data.submit, &data.server) {
        submit(server, &dir, task.id.as_str(), name)?;
    }
    Ok(())
}

/// Training allocates and frees tensors of up to hundreds of megabytes every step (CDT's attention at batch 2048
/// is 105 MB per tensor). glibc serves each from a fresh `mmap` and unmaps it on free, so every step faults all of
/// that memory in again: measured on CDT, 2 minutes of kernel time over 3 steps. Keeping freed memory in the heap
/// (no mmap, no trimming below 2 GB, growth in 1 GB steps) cut a step from ~100 s to ~35 s on the same loaded
/// machine (BENCHMARKS.md).
fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator tuning; called before any other thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_MAX, 0);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
        libc::mallopt(libc::M_TOP_PAD, 1 << 30);
    }
}

impl Command {
    /// The data arguments of a training command.
    fn data(&self) -> Option<&DataArgs> {
        match self {
            Command::Bc { data, .. }
            | Command::Bcql { data }
            | Command::Cdt { data }
            | Command::Bearl { data }
            | Command::Cpq { data }
            | Command::Coptidice { data }
            | Command::Caps { data }
            | Command::Fisor { data }
            | Command::Lspc { data } => Some(data),
            Command::Parity { .. } | Command::ReferenceEntry { .. } => None,
        }
    }
}

impl DataArgs {
    /// Everything that can be checked before training starts, so a mistake costs no training time: the task, the
    /// dataset file, the filter, the thresholds, the budget, the device, the output folder, and the entry's name
    /// and token for --submit (the server's own name rule).
    fn check(&self) -> anyhow::Result<()> {
        let catalog = Catalog::embedded()?;
        let task = catalog.get(&self.task)?;
        if let Some(file) = &self.dataset {
            anyhow::ensure!(file.is_file(), "--dataset {}: no such file", file.display());
        }
        if let Some(filter) = &self.filter {
            dsrl_filters::spec::FilterSpec::parse(filter, task).map_err(|e| anyhow::anyhow!("--filter: {e}"))?;
        }
        anyhow::ensure!(
            self.cost_thresholds.iter().all(|k| k.is_finite() && *k >= 0.0),
            "--cost-threshold: every threshold must be a finite number of at least 0"
        );
        anyhow::ensure!(self.steps >= 1, "--steps must be at least 1");
        anyhow::ensure!(self.batch_size != Some(0), "--batch-size must be at least 1");
        dsrl_train::training_device(&self.device)?;
        if let Some(out) = &self.out {
            std::fs::create_dir_all(out).map_err(|e| anyhow::anyhow!("--out {}: {e}", out.display()))?;
        }
        if let Some(name) = &self.submit {
            dsrl_suite::names::check_name("--submit entry name", name).map_err(anyhow::Error::msg)?;
            anyhow::ensure!(
                std::env::var_os("DSRL_TOKEN").is_some(),
                "--submit needs a user token in $DSRL_TOKEN"
            );
        }
        Ok(())
    }
}

fn main() -> anyhow::Result<()> {
    // SAFETY: first thing in main, before the runtime or any other thread exists.
    unsafe { dsrl_policy::pin_candle_threads() };
    keep_freed_memory();
    let command = Args::parse().command;
    if let Some(data) = command.data() {
        data.check()?;
    }
    match command {
        Command::Bc { mode, data } => train_bc(mode, data),
        Command::Bcql { data } => per_threshold("bcql", data, BcqlLearner::on_device),
        Command::Bearl { data } => per_threshold("bearl", data, BearlLearner::on_device),
        Command::Cpq { data } => per_threshold("cpq", data, CpqLearner::on_device),
        Command::Coptidice { data } => per_threshold("coptidice", data, CoptidiceLearner::on_device),
        Command::Cdt { data } => train_cdt(data),
        Command::Caps { data } => train_caps(data),
        Command::Fisor { data } => train_fisor(data),
        Command::Lspc { data } => train_lspc(data),
        Command::Parity { dir } => dsrl_train::parity::run(&dir),
        Command::ReferenceEntry {
            model,
            submission,
            reproduce,
            method,
            results,
        } => reference_entry(&model, submission.as_deref(), reproduce, &method, &results),
    }
}

/// `reference-entry`: the results-file line of a scored entry, or (`--reproduce`) its training record renewed.
fn reference_entry(
    model: &std::path::Path,
    submission: Option<&std::path::Path>,
    reproduce: bool,
    method: &str,
    results: &std::path::Path,
) -> anyhow::Result<()> {
    let entry = match submission {
        Some(submission) => dsrl_train::reference::record(model, submission, method, results)?,
        None => {
            debug_assert!(reproduce, "clap requires one of the two");
            dsrl_train::reference::reproduce(model, method, results)?
        }
    };
    out!(
        "{} {} seed {}: {} episodes under protocol {}, checkpoints {} trained by {} -> {}",
        entry.task,
        entry.method,
        entry.seed,
        entry.episodes.len(),
        entry.protocol_version,
        dsrl_suite::ids::short_hex(&entry.checkpoint_sha256),
        entry.code_commit,
        results.display()
    );
    Ok(())
}

/// BC-All (one model on every episode) or BC-Safe (one per threshold, on the episodes within it).
fn train_bc(mode: Mode, data: DataArgs) -> anyhow::Result<()> {
    let DataArgs {
        task,
        cost_thresholds,
        steps,
        seed,
        out,
        submit: submit_as,
        batch_size,
        ..
    } = &data;
    let (cost_thresholds, steps, seed, batch_size) = (cost_thresholds.clone(), *steps, *seed, *batch_size);
    let device = dsrl_train::training_device(&data.device)?;
    let catalog = Catalog::embedded()?;
    let task = catalog.get(task)?.clone();
    let (path, dataset_version, data_read) = load_data(&data, &task)?;
    let server = data.server.clone();
    let data = data_read;
    let out = out
        .clone()
        .unwrap_or_else(|| PathBuf::from("policies").join(task.id.as_str()));
    let default = BcSettings::default();
    let settings = BcSettings {
        steps,
        seed,
        batch_size: batch_size.unwrap_or(default.batch_size),
        ..default
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
        let mut learner = BcLearner::on_device(&settings, &obs, &act, data.obs_dim, data.act_dim, &device)?;
        let trained = train_loop(steps, &name, 500, 1, || Ok(vec![("mse", learner.step()?)]))?;
        let (loss, seconds) = (trained.figures.first().map_or(f64::NAN, |f| f.1), trained.seconds);
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
            "code_commit": CODE_COMMIT,
            "device": dsrl_train::device_name(&device),
            "cpu": cpu_model(),
            "final_mse": loss,
            "seconds": seconds,
            "cpu_seconds": trained.cpu_seconds,
            "first_step_seconds": trained.first_step_seconds,
        });
        learner
            .write(&dir, task.id.as_str(), &settings.hidden_sizes, conditioning, training)
            .with_context(|| format!("writing {}", dir.display()))?;
        out!(
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
