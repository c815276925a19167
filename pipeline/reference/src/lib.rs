//! `dsrl-admin reference`: the leaderboard's reference entries, made from the committed plan
//! (`data/reference/plan.toml`). A phase trains its models with `dsrl-train` (single-threaded, `jobs` at a time, one
//! pool per run), has a scoring server score each entry on the held seeds (the task's three thresholds × 20
//! episodes), and writes every scored entry into its results file with `dsrl-train reference-entry`. Every reference
//! table in the documents is generated from those files, and every server imports `results.jsonl`.
//!
//! Resumable: everything lives in the phase's state folder (`state.rs`), outside the clone. A model whose training
//! finished is not trained again; a submission already made is waited for, not made again; an entry the results
//! file already holds, trained to the same budget on the dataset the phase trains on, is neither trained nor
//! submitted, so a fresh machine resumes from the committed results. Kill it and run the same command again.
//!
//! The parts, in the order a phase uses them: `plan` (what to train), `server` (the private scoring server),
//! `training` (the pool of `dsrl-train` processes), `scoring` (submissions and the results file).

pub mod plan;
mod scoring;
mod server;
mod state;
mod training;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context;
use dsrl_client::api::Client;
use dsrl_client::cache::{Cache, FetchOptions};
use dsrl_suite::Catalog;
use tokio::signal::unix::{SignalKind, signal};

use dsrl_pipeline::full::now_rfc3339;
use dsrl_pipeline::identities::Identities;
use plan::{Dataset, Phase, Plan};
use scoring::{Scorer, Wait};
use state::{EntryKey, StateDir};
use training::{Model, Pool};

/// How often, while models train, trained entries are handed in and finished scorings recorded.
const LOOK_EVERY: Duration = Duration::from_secs(60);

/// What `dsrl-admin reference` was asked to do.
#[derive(Debug, Clone)]
pub struct Options {
    pub plan: PathBuf,
    /// Phases to run, in this order.
    pub phases: Vec<String>,
    /// Only these tasks of the phases (all when empty).
    pub tasks: Vec<String>,
    /// Models trained at once, one core each.
    pub jobs: usize,
    /// Evaluators of the private scoring server.
    pub evaluators: u32,
    /// The phases' state folder instead of `~/.dsrl/<phase's state>`.
    pub state: Option<PathBuf>,
    /// The results file instead of the phases'.
    pub results: Option<PathBuf>,
    /// Where the full builds are (`dsrl-admin build --root`).
    pub full_builds: PathBuf,
    /// Full-build phases take only the tasks whose build is finished under `full_builds`.
    pub built_here: bool,
    /// Train, submit nothing.
    pub train_only: bool,
    /// Train the recorded entries again from scratch and compare their checkpoints with the scored ones.
    pub reproduce: bool,
    /// Deal the models over this many GPUs (a CUDA build of dsrl-train).
    pub gpus: u32,
    /// A scoring server to use instead of a private one, with a user's token and that user's name.
    pub server: Option<String>,
    pub token: Option<String>,
    pub user: Option<String>,
    pub train_binary: PathBuf,
    pub server_binary: PathBuf,
    /// The clone's root: the starters, the committed identities, relative results paths.
    pub repo: PathBuf,
}

/// Runs the phases in turn. Everything that can be checked is checked before anything trains.
pub async fn run(options: &Options) -> anyhow::Result<()> {
    let plan = Plan::load(&options.plan)?;
    let phases = plan.phases(&options.phases)?;
    anyhow::ensure!(options.jobs >= 1, "--jobs must be at least 1");
    anyhow::ensure!(options.evaluators >= 1, "--evaluators must be at least 1");
    anyhow::ensure!(
        !options.built_here || phases.iter().all(|p| p.dataset == Dataset::FullBuild),
        "--built-here chooses among full builds: name full-build phases only"
    );
    let catalog = Catalog::embedded()?;
    for task in &options.tasks {
        catalog.get(task)?;
    }
    if options.server.is_some() {
        anyhow::ensure!(
            options.token.is_some() && options.user.is_some(),
            "a --server needs a user's token (--token or DSRL_TOKEN) and that user's name (--user or DSRL_USER)"
        );
        anyhow::ensure!(
            phases.iter().all(|p| p.dataset == Dataset::Starter),
            "a full-build phase hosts the builds on its private scoring server: leave --server out"
        );
    }
    for binary in [&options.train_binary]
        .into_iter()
        .chain(options.server.is_none().then_some(&options.server_binary))
    {
        anyhow::ensure!(
            which(binary).is_some(),
            "{} not found (build it, or name it with DSRL_TRAIN / DSRL_SERVER_BIN)",
            binary.display()
        );
    }
    let identities = Identities::read(&catalog, &options.repo)?;
    for phase in phases {
        eprintln!(
            "{} reference entries: phase {} ({})",
            now_rfc3339(),
            phase.name,
            phase.about
        );
        run_phase(phase, options, &catalog, &identities).await?;
    }
    Ok(())
}

/// The entries of a phase still to make, and the dataset version each task trains on.
struct Work {
    entries: Vec<EntryKey>,
    models: Vec<Model>,
    /// The tasks with models to train, in order, each with the version its models must train on.
    tasks: Vec<(String, String)>,
}

async fn run_phase(phase: &Phase, options: &Options, catalog: &Catalog, identities: &Identities) -> anyhow::Result<()> {
    let home = std::env::var_os("HOME").map(PathBuf::from).unwrap_or_default();
    let state = StateDir::new(
        options
            .state
            .clone()
            .unwrap_or_else(|| home.join(".dsrl").join(&phase.state)),
        options.reproduce,
    );
    let results = options
        .results
        .clone()
        .unwrap_or_else(|| options.repo.join(&phase.results));
    let work = plan_work(phase, options, catalog, identities, &results)?;
    if work.models.is_empty() {
        eprintln!(
            "every entry of phase {} is in {} already",
            phase.name,
            results.display()
        );
        return Ok(());
    }
    std::fs::create_dir_all(&state.root)?;

    // The scoring server: the one given, or a private one (stopped when this function returns).
    let (private, url, token, user) = match &options.server {
        Some(url) => (
            None,
            url.clone(),
            options.token.clone(),
            options.user.clone().unwrap_or_default(),
        ),
        None => {
            let private =
                server::PrivateServer::start(&options.server_binary, &state.root, &options.repo, options.evaluators)
                    .await?;
            if phase.dataset == Dataset::FullBuild {
                host_full_builds(&work, options, &private).await?;
            }
            let (url, token) = (private.url.clone(), Some(private.token.clone()));
            (Some(private), url, token, server::USER.to_owned())
        }
    };
    let client = Client::new(&url)?.with_token(token);
    fetch_datasets(&client, phase, &work).await?;

    let trained_tasks: Vec<&str> = work.tasks.iter().map(|(t, _)| t.as_str()).collect();
    eprintln!(
        "{} training {} models ({} at a time) of {} into {}",
        now_rfc3339(),
        work.models.len(),
        options.jobs,
        trained_tasks.join(" "),
        state.policies().display()
    );
    let mut pool = Pool::new(
        work.models.clone(),
        options.jobs,
        options.train_binary.clone(),
        url.clone(),
        state.clone(),
    );
    let mut scorer = Scorer::new(
        client,
        user,
        options.train_binary.clone(),
        results.clone(),
        state.clone(),
    );
    let bar = progress_bar(pool.total);
    let mut pending = work.entries.clone();
    let mut unreproduced: Vec<String> = Vec::new();
    let mut stop = Stop::new()?;
    let mut next_look = Instant::now();
    loop {
        let training = pool.step()?;
        bar.set_position(pool.trained);
        if !training || Instant::now() >= next_look {
            // Each method is handed in as soon as its own models have trained, whichever task it is of.
            let (ready, rest): (Vec<_>, Vec<_>) = pending
                .into_iter()
                .partition(|e| training::trained(&work.models, e, &state));
            pending = rest;
            if !options.train_only {
                hand_in(ready, options, &results, &mut scorer, &mut unreproduced).await?;
            }
            bar.set_message(format!(
                "{} scored and recorded, {} being scored",
                scorer.recorded,
                scorer.in_flight()
            ));
            next_look = Instant::now() + LOOK_EVERY;
        }
        if !training {
            break;
        }
        tokio::select! {
            _ = tokio::time::sleep(Duration::from_secs(1)) => {}
            stopped = stop.requested() => return Err(stopped),
        }
    }
    bar.finish_and_clear();
    if options.train_only {
        return Ok(());
    }
    if options.reproduce {
        anyhow::ensure!(unreproduced.is_empty(), "not reproduced: {}", unreproduced.join("; "));
        eprintln!(
            "{} every entry reproduced; {} names the commit of {}",
            now_rfc3339(),
            results.display(),
            options.train_binary.display()
        );
        return Ok(());
    }
    tokio::select! {
        done = scorer.record_finished(Wait::UntilEnded) => done?,
        stopped = stop.requested() => return Err(stopped),
    }
    eprintln!(
        "{} every entry scored and recorded in {}",
        now_rfc3339(),
        results.display()
    );
    drop(private);
    Ok(())
}

/// Hands in entries whose models have all trained: submits each (or, with --reproduce, compares its retrained
/// checkpoints with the scored ones, adding those that differ to `unreproduced`), then records the scorings that
/// have finished.
async fn hand_in(
    ready: Vec<EntryKey>,
    options: &Options,
    results: &Path,
    scorer: &mut Scorer,
    unreproduced: &mut Vec<String>,
) -> anyhow::Result<()> {
    for entry in ready {
        if !options.reproduce {
            scorer.submit(&entry).await?;
        } else if !reproduce(options, &scorer.state, results, &entry)? {
            unreproduced.push(entry.to_string());
        }
    }
    if !options.reproduce {
        scorer.record_finished(Wait::Look).await?;
    }
    Ok(())
}

/// SIGTERM and SIGINT stop a run, and its children with it; the same command resumes it.
struct Stop {
    terminate: tokio::signal::unix::Signal,
    interrupt: tokio::signal::unix::Signal,
}

impl Stop {
    fn new() -> std::io::Result<Stop> {
        Ok(Stop {
            terminate: signal(SignalKind::terminate())?,
            interrupt: signal(SignalKind::interrupt())?,
        })
    }

    /// Waits for a signal; the error says which and how to resume.
    async fn requested(&mut self) -> anyhow::Error {
        let name = tokio::select! {
            _ = self.terminate.recv() => "SIGTERM",
            _ = self.interrupt.recv() => "SIGINT",
        };
        anyhow::anyhow!("stopped by {name}; run the same command again to resume")
    }
}

/// Fetches each task's dataset once, so the parallel models read one verified cached file. The version hosted must
/// be the one the phase trains on (a committed identity), or the entries would name a dataset no other server can
/// host.
async fn fetch_datasets(client: &Client, phase: &Phase, work: &Work) -> anyhow::Result<()> {
    let cache = Cache::new(Cache::default_root());
    for (task, version) in &work.tasks {
        let fetched = cache.fetch(client, task, "latest", &FetchOptions::default()).await?;
        anyhow::ensure!(
            &fetched.version == version,
            "{} hosts {} as {task}'s latest, but phase {} trains on {version} (the committed {})",
            client.base(),
            fetched.version,
            phase.name,
            if phase.dataset == Dataset::FullBuild {
                "full build"
            } else {
                "starter"
            }
        );
    }
    Ok(())
}

/// What a phase still has to make: its runs' entries less those its results file holds already (same budget,
/// seed and dataset version; with --reproduce, every entry), and their models.
fn plan_work(
    phase: &Phase,
    options: &Options,
    catalog: &Catalog,
    identities: &Identities,
    results: &Path,
) -> anyhow::Result<Work> {
    let recorded = match std::fs::read_to_string(results) {
        Ok(text) => dsrl_scoring::reference::read_results(&text, catalog)
            .with_context(|| format!("reading {}", results.display()))?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
        Err(e) => return Err(anyhow::anyhow!("reading {}: {e}", results.display())),
    };
    let mut work = Work {
        entries: Vec::new(),
        models: Vec::new(),
        tasks: Vec::new(),
    };
    let mut without_build: Vec<String> = Vec::new();
    let mut not_built_here: Vec<String> = Vec::new();
    let mut dealt = 0u32;
    for run in &phase.runs {
        let tasks = run
            .task_ids(catalog)
            .map_err(|e| anyhow::anyhow!("phase {}: {e}", phase.name))?;
        for task_id in tasks {
            if !options.tasks.is_empty() && !options.tasks.contains(&task_id) {
                continue;
            }
            let version = match phase.dataset {
                Dataset::Starter => identities.starters().get(&task_id).cloned(),
                Dataset::FullBuild => identities.full_build(&task_id).map(str::to_owned),
            };
            let Some(version) = version else {
                without_build.push(task_id);
                continue;
            };
            if options.built_here && !dsrl_pipeline::full::finished(&options.full_builds.join(&task_id), &task_id)? {
                not_built_here.push(task_id);
                continue;
            }
            let task = catalog.get(&task_id)?;
            let before = work.models.len();
            for &seed in &run.seeds {
                for &method in &run.methods {
                    let steps = run.steps_of(method);
                    let entry = EntryKey {
                        task: task_id.clone(),
                        seed,
                        method,
                    };
                    let holding = recorded.iter().find(|e| {
                        e.task == task_id
                            && e.method == method.name()
                            && e.seed == seed
                            && e.training.steps == steps
                            && e.training.batch_size == run.batch_size.unwrap_or(e.training.osrl_batch_size)
                            && e.dataset_version == version
                    });
                    if let (Some(e), false) = (holding, options.reproduce) {
                        eprintln!(
                            "{entry} is in {} already ({steps} steps, batch {}, dataset {}); not trained again",
                            results.display(),
                            e.training.batch_size,
                            dsrl_suite::ids::short_hex(&version)
                        );
                        continue;
                    }
                    for threshold in training::models_of(method, &task.cost_thresholds) {
                        let device = (options.gpus > 0).then(|| {
                            dealt += 1;
                            format!("cuda:{}", (dealt - 1) % options.gpus)
                        });
                        work.models.push(Model {
                            entry: entry.clone(),
                            threshold,
                            steps,
                            batch: run.batch_size,
                            device,
                            dataset_version: version.clone(),
                        });
                    }
                    work.entries.push(entry);
                }
            }
            if work.models.len() > before && !work.tasks.iter().any(|(t, _)| t == &task_id) {
                work.tasks.push((task_id, version));
            }
        }
    }
    if !not_built_here.is_empty() {
        eprintln!(
            "phase {}: {} task(s) have a committed full build that is not finished under {}, left out (--built-here): {}",
            phase.name,
            not_built_here.len(),
            options.full_builds.display(),
            not_built_here.join(" ")
        );
    }
    if !without_build.is_empty() {
        eprintln!(
            "phase {}: {} task(s) have no committed full build yet, left out: {}",
            phase.name,
            without_build.len(),
            without_build.join(" ")
        );
    }
    Ok(work)
}

/// Uploads each trained task's finished full build to the private server as its `latest` (checked against its
/// committed identity by the build command). A task whose build is not finished here stops the phase first.
async fn host_full_builds(work: &Work, options: &Options, server: &server::PrivateServer) -> anyhow::Result<()> {
    let tasks: Vec<String> = work.tasks.iter().map(|(t, _)| t.clone()).collect();
    for task in &tasks {
        anyhow::ensure!(
            dsrl_pipeline::full::finished(&options.full_builds.join(task), task)?,
            "{task} has no finished full build under {} (dsrl-admin build {task})",
            options.full_builds.display()
        );
    }
    eprintln!(
        "hosting the full builds of {} from {} as their latest versions",
        tasks.join(" "),
        options.full_builds.display()
    );
    let build = dsrl_pipeline::full::BuildOptions {
        plan: options.repo.join(dsrl_pipeline::full::plan::PLAN_PATH),
        recipes: options.repo.join("data/recipes"),
        records: options.repo.join(dsrl_pipeline::full::record::RECORDS_DIR),
        root: options.full_builds.clone(),
        tasks,
        jobs: 1,
        workers: 1,
        // The builds it hosts are finished: their children only check and upload.
        retries: 0,
        record: false,
        server: Some(server.url.clone()),
        token: Some(server.admin_token.clone()),
        progress: false,
    };
    let outcomes = dsrl_pipeline::full::build(&build).await?;
    let failed: Vec<String> = outcomes
        .iter()
        .filter(|o| !o.ok() || o.uploaded.is_none())
        .map(dsrl_pipeline::full::describe)
        .collect();
    anyhow::ensure!(
        failed.is_empty(),
        "hosting the full builds failed: {}",
        failed.join("; ")
    );
    Ok(())
}

/// Trains an entry's checkpoints again (done by the pool) and has `dsrl-train reference-entry --reproduce` compare
/// them with the scored ones; false when they differ (the entry is left as it is).
fn reproduce(options: &Options, state: &StateDir, results: &Path, entry: &EntryKey) -> anyhow::Result<bool> {
    Ok(scoring::reference_entry(&options.train_binary, state, entry, results, None)?.success())
}

fn progress_bar(models: u64) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(models);
    bar.set_style(
        indicatif::ProgressStyle::with_template("models {pos}/{len} {wide_bar} {elapsed_precise} (eta {eta}) {msg}")
            .expect("a valid template"),
    );
    bar
}

/// A program path as given, or found on PATH.
fn which(program: &Path) -> Option<PathBuf> {
    if program.components().count() > 1 {
        return program.is_file().then(|| program.to_owned());
    }
    std::env::split_paths(&std::env::var_os("PATH")?)
        .map(|dir| dir.join(program))
        .find(|p| p.is_file())
}
