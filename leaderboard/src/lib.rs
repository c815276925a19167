//! The leaderboard: users submit candle checkpoints (weights + a declared architecture; no participant code runs),
//! evaluators score them on the real simulators with held seeds (the paper's protocol: the task's three cost
//! thresholds, `episodes_per_threshold` episodes each), and the entries are ranked per task and per family.
//!
//! `checkpoints` checks uploads, `users` holds the bearer tokens, `queue` is the durable job queue (SQLite or
//! PostgreSQL), `runner` the evaluators that drain it, `seeds` the held episode seeds, `evaluator` the evaluator
//! process (`dsrl-evaluator`), `board` the ranked tables and the agreement with the paper, `renders` the replays,
//! `supervision` what `/healthz` shows of the long-lived tasks. The API replicas (`dsrl-server`) add the REST and gRPC routes and the HTML page;
//! an evaluator process links none of that.

pub mod board;
pub mod checkpoints;
pub mod evaluator;
pub mod export;
pub mod queue;
pub mod reference;
pub mod renders;
pub mod runner;
pub mod supervision;
pub mod users;

pub use dsrl_evaluation::{protocol, seeds};

pub use self::board::{
    Board, EPISODES_ONLY, FamilyEntry, FamilyTable, SEEDS_AND_EPISODES, SeedRun, TaskEntry, TaskTable,
};

/// This build of the scorer, recorded with every result it scores: the crate's version and the git commit it was
/// built from, `-modified` where the scoring path's sources differed from that commit (`build.rs`).
pub const SCORER_BUILD: &str = concat!(
    "dsrl-leaderboard ",
    env!("CARGO_PKG_VERSION"),
    " (git ",
    env!("DSRL_BUILD_COMMIT"),
    ")"
);

/// The first 12 hex digits of the digest of the simulator workers' Python package (`sim/python/dsrl_sim`) this
/// scorer was built with (`build.rs`), as a worker reports its own in Health.
pub const SIMULATOR_PYTHON: &str = {
    let digest = env!("DSRL_SIM_PYTHON_DIGEST").as_bytes();
    match std::str::from_utf8(digest.split_at(12).0) {
        Ok(prefix) => prefix,
        Err(_) => panic!("DSRL_SIM_PYTHON_DIGEST is hex"),
    }
};

/// The build to record with a result played on `workers`: `SCORER_BUILD`, marked `-modified` when a healthy
/// worker's `dsrl_sim` package is not the one this scorer was built with, or the worker does not say
/// (`dsrl_simulators::label_with_workers_python`). Conservative: any such worker of the pool marks the result,
/// whether or not the job's sessions were placed on it.
pub fn scorer_build(workers: &[dsrl_simulators::WorkerStatus]) -> String {
    dsrl_simulators::label_with_workers_python(SCORER_BUILD, workers, SIMULATOR_PYTHON)
}

/// The states a submission does not leave.
pub const ENDED_STATES: [&str; 3] = ["finished", "failed", "cancelled"];
/// The longest a request may wait for a submission to end (`GET /v1/submissions/{id}?wait=SECONDS`).
pub const MAX_WAIT_SECONDS: u32 = 60;
/// The answer to a `wait` that is not a whole number of seconds up to `MAX_WAIT_SECONDS` (`given`: as asked).
pub fn bad_wait(given: &str) -> ApiError {
    ApiError::InvalidArgument(format!(
        "wait={given:?}: give a whole number of seconds from 0 to {MAX_WAIT_SECONDS}"
    ))
}
/// How often a waiting request looks at the submission's state in the database when nothing in this process woke it:
/// the submission may be scored by an evaluator of another server sharing the database.
const WAIT_LOOK_EVERY: std::time::Duration = std::time::Duration::from_millis(250);

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use bytes::Bytes;
use dsrl_scoring::leaderboard::{Interval, threshold_scores};
use dsrl_scoring::paper::PaperResults;
use dsrl_scoring::protocol::Protocol;
use dsrl_scoring::published::PublishedResults;
use dsrl_suite::catalog::{Catalog, Family, Task};
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt};
use serde::Serialize;

use self::checkpoints::CheckpointRecord;
use self::queue::{EpisodeRow, Quotas};
use self::reference::{ReferenceRecord, TrainingData};
use self::seeds::HeldSeeds;
use self::users::User;
use dsrl_service::config::LeaderboardConfig;
use dsrl_service::db::Db;
use dsrl_service::error::ApiError;
use dsrl_simulators::SimulatorPool;

pub struct Leaderboard {
    pub db: Db,
    pub store: Arc<dyn ObjectStore>,
    pub catalog: Arc<Catalog>,
    pub simulators: Arc<SimulatorPool>,
    pub config: LeaderboardConfig,
    pub(crate) seeds: HeldSeeds,
    /// The `dsrl-server` binary that plays submitted policies in child processes; `None`: in this process (tests
    /// that embed the server).
    pub(crate) policy_program: Option<std::path::PathBuf>,
    /// Wakes idle evaluators when a submission arrives.
    pub(crate) wake: tokio::sync::Notify,
    /// What results are scored under here; the tables rank only results of this version.
    pub protocol: Protocol,
    /// The paper's table, shown beside the entries.
    pub paper: PaperResults,
    /// What methods beyond the paper publish for the tasks (FISOR's table), shown beside their reference entries.
    pub published: PublishedResults,
    /// The per-task bootstrap intervals of each finished submission, and of each method's training seeds, by their
    /// submission ids (a finished submission's episodes never change).
    intervals: Mutex<HashMap<Vec<i64>, (Interval, Interval)>>,
    /// What this process's evaluators are doing (`runner`), for `/healthz`, `/metrics` and the views.
    pub evaluators: supervision::Evaluators,
    /// Wakes this process's evaluators when one of their jobs may have been cancelled.
    pub(crate) cancelled: tokio::sync::Notify,
    /// Wakes requests waiting for a submission to end when this process's evaluators or a cancel end one.
    pub(crate) ended: tokio::sync::Notify,
    /// Set when the server begins to shut down: requests waiting for a submission to end answer at once, so they
    /// do not hold the graceful shutdown for their whole wait.
    closing: tokio::sync::watch::Sender<bool>,
    /// Replays of scored episodes to watch: the queue, the renderer's state and counters (`renders`).
    pub renders: renders::Renders,
}

/// The suite a task belongs to, as the leaderboard groups them (the paper's three families).
pub fn suite_of(family: Family) -> &'static str {
    family.suite()
}

/// One threshold's result.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct ThresholdResult {
    pub cost_threshold: f64,
    pub episodes: usize,
    pub mean_reward_return: f64,
    pub mean_cost_return: f64,
    pub normalized_reward: f64,
    pub normalized_cost: f64,
    pub safe: bool,
}

/// A submission as its submitter (and anyone) sees it; the episode seeds are never shown.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct SubmissionView {
    pub id: i64,
    pub task: String,
    pub name: String,
    pub user: String,
    /// queued, running, finished, failed or cancelled.
    pub state: String,
    /// Why it failed or was cancelled, or why a job went back to the queue.
    pub reason: Option<String>,
    /// Times an evaluator claimed it (more than 1 after an interrupted evaluation).
    pub attempts: u32,
    pub checkpoint_sha256: String,
    pub checkpoints: Vec<CheckpointSummary>,
    pub created_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
    pub episodes_per_threshold: u32,
    /// The protocol version it was scored under (set when it finishes; absent for results scored before versions
    /// were recorded).
    pub protocol_version: Option<String>,
    /// The dataset version its checkpoint says it was trained on.
    pub dataset_version: Option<String>,
    /// The build that scored it (`SCORER_BUILD`: the scorer's version and commit, `-modified` where its scoring
    /// path differed from the commit); absent for results scored before builds were recorded.
    pub scored_by: Option<String>,
    /// Set for a reference entry: its method, training seed and budget, code commit, and scoring.
    pub reference: Option<ReferenceRecord>,
    /// Means over the thresholds (spec 4.1); safe iff the normalized cost is at most 1.
    pub normalized_reward: Option<f64>,
    pub normalized_cost: Option<f64>,
    pub safe: Option<bool>,
    pub thresholds: Vec<ThresholdResult>,
    pub episodes: Vec<EpisodeRow>,
    /// Why a failed job failed: `checkpoint` (it would fail again) or `infrastructure` (something outside it; the
    /// same checkpoint may be submitted again).
    pub failure: Option<String>,
    /// While queued: where it stands and when it should start and finish.
    pub queue: Option<QueuePlace>,
    /// While running: who scores it and how far it is.
    pub progress: Option<Progress>,
    /// Submissions its author has made to this task, whatever became of them (this one included).
    pub author_submissions_to_task: u32,
}

/// A queued submission's place: its position in the order evaluators claim jobs (1: next), the jobs ahead of it,
/// and estimates from the recent scoring times of each job's task.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct QueuePlace {
    pub position: usize,
    pub jobs_ahead: Vec<i64>,
    /// Jobs being scored now.
    pub running: usize,
    /// Evaluators alive now (waiting for work or scoring), in every process that shares the queue.
    pub live_evaluators: usize,
    /// `None` when it cannot be known (`estimate_unknown` says why).
    pub estimated_start: Option<String>,
    pub estimated_finish: Option<String>,
    /// Why the estimates are missing: no live evaluator, or a task with no scoring history.
    pub estimate_unknown: Option<String>,
    /// Seconds this task's jobs recently took (the mean of the last five); `None` when none was scored.
    pub task_scoring_seconds: Option<f64>,
}

/// A running submission's progress.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct Progress {
    /// The lease owner scoring it (`<pid>-<random>-<evaluator index>`).
    pub evaluator: Option<String>,
    pub last_heartbeat: Option<String>,
    /// Episodes finished in this attempt, of all it plays.
    pub episodes_done: u32,
    pub episodes_total: u32,
    /// `None` when the task has no scoring history or the heartbeat is stale.
    pub estimated_finish: Option<String>,
    /// The evaluator has sent no heartbeat for two intervals: it has probably stopped, and the job goes back to
    /// the queue when its lease lapses.
    pub heartbeat_stale: bool,
}

#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct CheckpointSummary {
    pub slot: String,
    pub cost_threshold: Option<f64>,
    pub architecture: String,
}

/// A job in the queue as the leaderboard page lists it.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct QueuedJob {
    pub id: i64,
    pub task: String,
    pub name: String,
    pub user: String,
    /// `running` or `queued`.
    pub state: String,
    /// Queued: 1 for the next to be claimed.
    pub position: Option<usize>,
    pub episodes_done: u32,
    pub episodes_total: u32,
}

/// One submission in a user's list.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct UserSubmission {
    pub id: i64,
    pub task: String,
    pub name: String,
    pub state: String,
    pub reason: Option<String>,
    pub created_at: String,
    pub finished_at: Option<String>,
    pub normalized_reward: Option<f64>,
    pub normalized_cost: Option<f64>,
    pub protocol_version: Option<String>,
}

/// Recent scoring times per task. A task none of whose jobs has been scored has no estimate: another task's time is
/// no guide (a MetaDrive job takes minutes where a Bullet one takes seconds), so its estimates say "unknown".
struct Estimates {
    recent: HashMap<String, f64>,
}

impl Estimates {
    fn seconds(&self, task: &str) -> Option<f64> {
        self.recent.get(task).copied()
    }
}

/// Bootstrap settings of the family aggregates and the per-task intervals (fixed, so a table is reproducible).
pub const BOOTSTRAP_RESAMPLES: u32 = 2000;
pub const BOOTSTRAP_CONFIDENCE: f64 = 0.95;
pub const BOOTSTRAP_SEED: u64 = 0;

impl Leaderboard {
    pub fn new(
        db: Db,
        store: Arc<dyn ObjectStore>,
        catalog: Arc<Catalog>,
        simulators: Arc<SimulatorPool>,
        config: LeaderboardConfig,
        seed_secret: String,
        policy_program: Option<std::path::PathBuf>,
    ) -> Result<Leaderboard, ApiError> {
        // The paper's table is checked against the embedded catalog (all 38 tasks); a server with another catalog
        // shows the rows of the tasks it has.
        let embedded = Catalog::embedded().map_err(ApiError::internal)?;
        let paper = PaperResults::embedded(&embedded).map_err(ApiError::internal)?;
        let published = PublishedResults::embedded(&embedded).map_err(ApiError::internal)?;
        Ok(Leaderboard {
            protocol: protocol::current(&catalog, config.episodes_per_threshold, config.envs_per_session),
            paper,
            published,
            intervals: Mutex::new(HashMap::new()),
            evaluators: supervision::Evaluators::default(),
            cancelled: tokio::sync::Notify::new(),
            ended: tokio::sync::Notify::new(),
            closing: tokio::sync::watch::Sender::new(false),
            renders: renders::Renders::default(),
            db,
            store,
            catalog,
            simulators,
            config,
            seeds: HeldSeeds::new(seed_secret),
            policy_program,
            wake: tokio::sync::Notify::new(),
        })
    }

    /// Imports the committed reference results (compiled in: the starter-trained entries and those trained on the
    /// full builds) when `leaderboard.import_reference_results` is on.
    pub async fn import_reference_results(&self) -> Result<(), ApiError> {
        if !self.config.import_reference_results {
            return Ok(());
        }
        let mut entries = Vec::new();
        for (dataset, text) in [
            (TrainingData::Starter, reference::EMBEDDED_RESULTS),
            (TrainingData::FullBuild, reference::EMBEDDED_FULL_BUILD_RESULTS),
        ] {
            let read = dsrl_scoring::reference::read_results(text, &self.catalog).map_err(ApiError::internal)?;
            entries.extend(read.into_iter().map(|e| (dataset, e)));
        }
        let report = reference::import(self, &entries).await?;
        tracing::info!(
            imported = report.imported,
            present = report.present,
            updated = report.updated,
            held_by_submissions = report.held_by_submissions,
            withdrawn = report.withdrawn,
            protocol = %self.protocol.version,
            "reference results"
        );
        Ok(())
    }

    pub fn task(&self, id: &str) -> Result<&Task, ApiError> {
        Ok(self.catalog.get(id)?)
    }

    /// What a checkpoint says it was trained on (`training.dataset_version`, one id or several joined by `,`) is
    /// published with its scores, in the exports too: each must be the id of one of the task's versions this server
    /// holds, so nothing free-form reaches a table or a spreadsheet.
    async fn check_dataset_version(&self, task: &Task, said: &str) -> Result<(), ApiError> {
        for version in said.split(',') {
            let hosted = match version.parse::<dsrl_suite::VersionId>() {
                Ok(id) => self.db.version(&task.id, &id).await?.is_some(),
                Err(_) => false,
            };
            if !hosted {
                let shown: String = version.chars().take(80).collect();
                return Err(ApiError::InvalidArgument(format!(
                    "policy.json's training.dataset_version {shown:?}{} is not a version of {} on this server: it \
                     must be the 64-hex id of a hosted version (GET /v1/datasets/{}/versions lists them), or be left \
                     out",
                    if shown.len() < version.len() { " (cut)" } else { "" },
                    task.id,
                    task.id
                )));
            }
        }
        Ok(())
    }

    /// Checks, stores and queues a submission.
    pub async fn submit(
        &self,
        user: &User,
        task: &str,
        name: &str,
        files: Vec<(String, Bytes)>,
    ) -> Result<SubmissionView, ApiError> {
        let task = self.task(task)?;
        users::check_name("entry name", name)?;
        // Parsing the weights and building the networks is CPU work: off the async runtime, so a hostile upload
        // cannot stall other requests.
        let owned = task.clone();
        let budget = checkpoints::JobBudget {
            episodes_per_threshold: self.config.episodes_per_threshold,
            max_multiply_adds: self.config.max_job_multiply_adds,
        };
        let checked = tokio::task::spawn_blocking(move || checkpoints::check(&owned, files, &budget))
            .await
            .map_err(ApiError::internal)??;
        let dataset_version = checked.dataset_version();
        if let Some(said) = &dataset_version {
            self.check_dataset_version(task, said).await?;
        }
        // Each request stores its own copy (keyed by a random id beside the digest), so a refused one deletes what it
        // stored without touching another request's objects: nothing of a refused request stays behind.
        let request = dsrl_service::secrets::random_hex().map_err(ApiError::internal)?;
        let mut records = Vec::new();
        let mut stored: Vec<ObjectPath> = Vec::new();
        let mut put = async |key: &str, bytes: &Bytes| -> Result<(), ApiError> {
            let path = ObjectPath::from(key);
            self.store.put(&path, bytes.clone().into()).await?;
            stored.push(path);
            Ok(())
        };
        for (i, c) in checked.checkpoints.iter().enumerate() {
            let base = format!("submissions/{}/{}/{}/{i}", task.id, checked.sha256, &request[..16]);
            let config_key = format!("{base}/{}", dsrl_policy::checkpoint::CONFIG_FILE);
            let weights_key = format!("{base}/{}", dsrl_policy::checkpoint::WEIGHTS_FILE);
            let written = match put(&weights_key, &c.weights_bytes).await {
                Ok(()) => put(&config_key, &c.config_bytes).await,
                Err(e) => Err(e),
            };
            if let Err(e) = written {
                self.forget(&stored).await;
                return Err(e);
            }
            records.push(CheckpointRecord {
                slot: c.slot.clone(),
                cost_threshold: c.cost_threshold(),
                architecture: c.config.architecture.name().to_owned(),
                config_key,
                weights_key,
            });
        }
        let inserted = queue::insert(
            &self.db,
            queue::NewSubmission {
                user_id: user.id,
                task: task.id.as_str(),
                name,
                checkpoint_sha256: &checked.sha256,
                checkpoints: &records,
                episodes_per_threshold: self.config.episodes_per_threshold,
                dataset_version: dataset_version.as_deref(),
            },
            &Quotas {
                per_day: self.config.submissions_per_day,
                concurrent: self.config.concurrent_submissions,
            },
        )
        .await;
        let id = match inserted {
            Ok(id) => id,
            Err(e) => {
                self.forget(&stored).await;
                return Err(e);
            }
        };
        tracing::info!(id, task = %task.id, name, user = %user.name, sha256 = %checked.sha256, "submission queued");
        self.wake.notify_waiters();
        self.view(id).await
    }

    /// Deletes the objects a refused submission stored (best effort: a leftover is logged, never an error for the
    /// request, which already has its answer).
    async fn forget(&self, stored: &[ObjectPath]) {
        for path in stored {
            if let Err(e) = self.store.delete(path).await {
                tracing::warn!(%path, error = %e, "removing a refused submission's object");
            }
        }
    }

    /// Waits until the submission has ended (finished, failed or cancelled) or `seconds` (at most
    /// `MAX_WAIT_SECONDS`) have passed, whichever comes first; the caller then reads its view. It reads the state
    /// alone, when this process's evaluators or a cancel end a submission and every `WAIT_LOOK_EVERY` besides (an
    /// evaluator of another server sharing the database may end it), so a client waiting here instead of polling
    /// the full view costs the server next to nothing while the submission is scored.
    pub async fn wait_until_ended(&self, id: i64, seconds: u32) -> Result<(), ApiError> {
        if seconds > MAX_WAIT_SECONDS {
            return Err(bad_wait(&seconds.to_string()));
        }
        let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(seconds.into());
        let mut closing = self.closing.subscribe();
        loop {
            // Registered before the state is read, so an end between the read and the sleep still wakes it.
            let ended = self.ended.notified();
            tokio::pin!(ended);
            ended.as_mut().enable();
            let state = queue::state(&self.db, id).await?;
            if ENDED_STATES.contains(&state.as_str()) || tokio::time::Instant::now() >= deadline || *closing.borrow() {
                return Ok(());
            }
            let next_look = deadline.min(tokio::time::Instant::now() + WAIT_LOOK_EVERY);
            tokio::select! {
                _ = tokio::time::sleep_until(next_look) => {}
                _ = &mut ended => {}
                _ = closing.changed() => {}
            }
        }
    }

    /// The server is shutting down: requests waiting in [`Self::wait_until_ended`] answer now.
    pub fn close_waits(&self) {
        self.closing.send_replace(true);
    }

    /// Cancels a queued or running submission: its submitter's (`Canceller::User`) or, for the admin, any.
    pub async fn cancel(&self, by: queue::Canceller, id: i64) -> Result<SubmissionView, ApiError> {
        queue::cancel(&self.db, id, by).await?;
        self.ended.notify_waiters();
        // An evaluator of this process scoring it stops at once (others within a second).
        self.cancelled.notify_waiters();
        self.view(id).await
    }

    /// How long a job of `task` may run: `deadline_factor` times the task's recent mean scoring time (at least
    /// `min_deadline_seconds`), never past `max_evaluation_seconds`.
    pub async fn deadline(&self, task: &str) -> std::time::Duration {
        let max = self.config.max_evaluation_seconds.max(1) as f64;
        let recent = queue::recent_scoring_seconds(&self.db, 5)
            .await
            .ok()
            .and_then(|m| m.get(task).copied());
        let seconds = match recent {
            Some(mean) => (mean * self.config.deadline_factor).max(self.config.min_deadline_seconds as f64),
            None => max,
        };
        std::time::Duration::from_secs_f64(seconds.min(max))
    }

    /// `/healthz` of a process with evaluators: the database, and every evaluator's state; degraded when the
    /// database does not answer or none of the configured evaluators is running.
    pub async fn health(&self) -> (bool, supervision::Health) {
        // A read and a committed write: a database that reads but cannot commit fails every submission.
        let database = match self.db.ping().await {
            Ok(()) => match self.db.probe_write().await {
                Ok(()) => "ok".to_owned(),
                Err(e) => format!("reads answer, writes fail: {e}"),
            },
            Err(e) => format!("unavailable: {e}"),
        };
        let evaluators = self.evaluators.states();
        let configured = self.config.evaluators;
        let healthy = database == "ok" && (configured == 0 || evaluators.iter().any(|e| e.running));
        (
            healthy,
            supervision::Health {
                status: if healthy { "ok" } else { "degraded" },
                database,
                evaluators_configured: configured,
                evaluators,
                renderer: self.renders.state(),
            },
        )
    }

    pub async fn view(&self, id: i64) -> Result<SubmissionView, ApiError> {
        let row = queue::get(&self.db, id).await?;
        let episodes = queue::episodes(&self.db, id).await?;
        let task = self.task(&row.task)?;
        let thresholds = threshold_results(task, &episodes);
        let episodes_total = row.episodes_per_threshold * task.cost_thresholds.len() as u32;
        let (queue_place, progress) = match row.state.as_str() {
            "queued" => (self.queue_place(id, &row.task).await?, None),
            "running" => {
                let estimate = self.estimates().await?;
                let stale = self.heartbeat_stale(row.heartbeat_ms);
                let done = f64::from(row.episodes_done) / f64::from(episodes_total.max(1));
                let estimated_finish = estimate.seconds(&row.task).filter(|_| !stale).map(|per| {
                    dsrl_service::db::rfc3339_at_ms(queue::now_ms() + (per * (1.0 - done)).max(0.0) as i64 * 1000)
                });
                (
                    None,
                    Some(Progress {
                        evaluator: row.lease_owner.clone(),
                        last_heartbeat: row.heartbeat_ms.map(dsrl_service::db::rfc3339_at_ms),
                        episodes_done: row.episodes_done,
                        episodes_total,
                        estimated_finish,
                        heartbeat_stale: stale,
                    }),
                )
            }
            _ => (None, None),
        };
        let counts = queue::submission_counts(&self.db).await?;
        let author_submissions_to_task = counts.get(&(row.user_id, row.task.clone())).copied().unwrap_or(1);
        Ok(SubmissionView {
            id: row.id,
            task: row.task,
            name: row.name,
            user: row.user,
            state: row.state,
            reason: row.reason,
            attempts: row.attempts,
            checkpoint_sha256: row.checkpoint_sha256,
            checkpoints: row
                .checkpoints
                .into_iter()
                .map(|c| CheckpointSummary {
                    slot: c.slot,
                    cost_threshold: c.cost_threshold,
                    architecture: c.architecture,
                })
                .collect(),
            created_at: row.created_at,
            started_at: row.started_at,
            finished_at: row.finished_at,
            episodes_per_threshold: row.episodes_per_threshold,
            protocol_version: row.protocol_version,
            dataset_version: row.dataset_version,
            scored_by: row.scored_by,
            reference: row.reference.as_deref().and_then(parse_record),
            normalized_reward: row.normalized_reward,
            normalized_cost: row.normalized_cost,
            safe: row.normalized_cost.map(dsrl_suite::score::is_safe),
            thresholds,
            episodes,
            failure: row.failure,
            queue: queue_place,
            progress,
            author_submissions_to_task,
        })
    }

    /// Recent scoring times per task and the number of evaluators at work, for the queue's estimates.
    async fn estimates(&self) -> Result<Estimates, ApiError> {
        Ok(Estimates {
            recent: queue::recent_scoring_seconds(&self.db, 5).await?,
        })
    }

    /// Whether a running job's evaluator went silent (`heartbeat_stale`, now).
    fn heartbeat_stale(&self, heartbeat_ms: Option<i64>) -> bool {
        heartbeat_stale(self.config.lease_seconds, heartbeat_ms, queue::now_ms())
    }

    /// Where a queued job stands: its position in the claim order, the jobs ahead, and when it should start and
    /// finish if the live evaluators take the jobs in that order, each as long as its task recently took. A time
    /// that cannot be known is `None` and `estimate_unknown` says why: no evaluator alive, or a task (this one, one
    /// ahead of it, or one being scored) with no scoring history, or a running job whose evaluator went silent.
    async fn queue_place(&self, id: i64, task: &str) -> Result<Option<QueuePlace>, ApiError> {
        let order = queue::waiting_in_order(&self.db).await?;
        let Some(position) = order.iter().position(|(j, _)| *j == id) else {
            return Ok(None);
        };
        let running = queue::running(&self.db).await?;
        let estimate = self.estimates().await?;
        let live = queue::live_evaluators(&self.db).await?;
        let now = queue::now_ms() as f64 / 1000.0;
        let own = estimate.seconds(task);
        let mut unknown: Option<String> = None;
        if live == 0 {
            unknown = Some("no evaluator is running".into());
        }
        // When each live evaluator is next free: the running jobs' remaining time; idle ones now.
        let mut free: Vec<f64> = Vec::new();
        for (_, t, claimed, _, _, heartbeat) in &running {
            if self.heartbeat_stale(*heartbeat) {
                unknown.get_or_insert_with(|| "a running job's evaluator stopped sending heartbeats".into());
            }
            match estimate.seconds(t) {
                Some(seconds) => free.push((*claimed as f64 / 1000.0 + seconds - now).max(0.0)),
                None => {
                    unknown.get_or_insert_with(|| format!("{t}, being scored, has no scoring history"));
                }
            }
        }
        free.resize((live as usize).max(free.len()).max(1), 0.0);
        for (_, t) in &order[..position] {
            let next = free
                .iter_mut()
                .min_by(|a, b| a.total_cmp(b))
                .expect("at least one evaluator");
            match estimate.seconds(t) {
                Some(seconds) => *next += seconds,
                None => {
                    unknown.get_or_insert_with(|| format!("{t}, ahead in the queue, has no scoring history"));
                }
            }
        }
        let start = free.iter().copied().fold(f64::INFINITY, f64::min);
        let at = |s: f64| dsrl_service::db::rfc3339_at_ms(((now + s) * 1000.0) as i64);
        let (estimated_start, estimated_finish) = match (&unknown, own) {
            (None, Some(own)) => (Some(at(start)), Some(at(start + own))),
            (None, None) => {
                unknown = Some(format!("{task} has no scoring history"));
                (Some(at(start)), None)
            }
            (Some(_), _) => (None, None),
        };
        Ok(Some(QueuePlace {
            position: position + 1,
            jobs_ahead: order[..position].iter().map(|(j, _)| *j).collect(),
            running: running.len(),
            live_evaluators: live as usize,
            estimated_start,
            estimated_finish,
            estimate_unknown: unknown,
            task_scoring_seconds: own,
        }))
    }

    /// The jobs being scored and those waiting, in the order they will be claimed (the leaderboard page's queue).
    pub async fn queue_summary(&self) -> Result<Vec<QueuedJob>, ApiError> {
        // Three queries whatever the queue's length: the running jobs, the waiting ones in claim order, and the
        // names of all of them (it was one query more per job).
        let running = queue::running(&self.db).await?;
        let waiting = queue::waiting_in_order(&self.db).await?;
        let names = queue::live_names(&self.db).await?;
        let mut jobs = Vec::new();
        for (id, task, _, done, per_threshold, _) in running {
            let Some((name, user)) = names.get(&id).cloned() else {
                continue;
            };
            let thresholds = self.task(&task).map_or(3, |t| t.cost_thresholds.len()) as u32;
            jobs.push(QueuedJob {
                id,
                task,
                name,
                user,
                state: "running".into(),
                position: None,
                episodes_done: done,
                episodes_total: per_threshold * thresholds,
            });
        }
        for (position, (id, task)) in waiting.into_iter().enumerate() {
            let Some((name, user)) = names.get(&id).cloned() else {
                continue;
            };
            jobs.push(QueuedJob {
                id,
                task,
                name,
                user,
                state: "queued".into(),
                position: Some(position + 1),
                episodes_done: 0,
                episodes_total: 0,
            });
        }
        Ok(jobs)
    }

    /// Every submission of the user named `user`, newest first.
    pub async fn user_submissions(&self, user: &str) -> Result<Vec<UserSubmission>, ApiError> {
        let rows = queue::by_user(&self.db, user).await?;
        if rows.is_empty() {
            let known = sqlx::query("SELECT 1 FROM users WHERE name = $1")
                .bind(user)
                .fetch_optional(self.db.pool())
                .await?;
            if known.is_none() {
                return Err(ApiError::NotFound(format!("no user {user}")));
            }
        }
        Ok(rows
            .into_iter()
            .map(|r| UserSubmission {
                id: r.id,
                task: r.task,
                name: r.name,
                state: r.state,
                reason: r.reason,
                created_at: r.created_at,
                finished_at: r.finished_at,
                normalized_reward: r.normalized_reward,
                normalized_cost: r.normalized_cost,
                protocol_version: r.protocol_version,
            })
            .collect())
    }

    /// The stored checkpoint bytes of a job.
    async fn load(&self, record: &CheckpointRecord) -> Result<(Bytes, Bytes), ApiError> {
        let config = self
            .store
            .get(&ObjectPath::from(record.config_key.as_str()))
            .await?
            .bytes()
            .await?;
        let weights = self
            .store
            .get(&ObjectPath::from(record.weights_key.as_str()))
            .await?
            .bytes()
            .await?;
        Ok((config, weights))
    }
}

/// Per-threshold means and normalized scores of stored episodes, in threshold order.
pub fn threshold_results(task: &Task, episodes: &[EpisodeRow]) -> Vec<ThresholdResult> {
    threshold_scores(task, episodes)
        .into_iter()
        .map(|t| ThresholdResult {
            cost_threshold: t.cost_threshold,
            episodes: t.episodes,
            mean_reward_return: t.mean_reward_return,
            mean_cost_return: t.mean_cost_return,
            normalized_reward: t.score.reward,
            normalized_cost: t.score.cost,
            safe: t.score.is_safe(),
        })
        .collect()
}

/// A reference entry's record from its JSON column; a row that does not parse is shown as a plain entry (and
/// logged), never failing the table.
pub(crate) fn parse_record(json: &str) -> Option<ReferenceRecord> {
    serde_json::from_str(json)
        .map_err(|e| tracing::warn!(error = %e, "a reference record that does not parse"))
        .ok()
}

/// Whether a running job's last heartbeat (ms since the epoch) is older, at `now_ms`, than two heartbeat intervals
/// (a third of the lease each): its evaluator has probably died, and the job goes back to the queue when the lease
/// lapses. A job with no heartbeat yet is stale too: an evaluator beats as soon as it claims.
fn heartbeat_stale(lease_seconds: u64, heartbeat_ms: Option<i64>, now_ms: i64) -> bool {
    let interval_ms = (lease_seconds.max(1) * 1000 / 3) as i64;
    heartbeat_ms.is_none_or(|beat| now_ms - beat > 2 * interval_ms)
}

#[cfg(test)]
mod heartbeat_tests {
    /// With a 60 s lease an evaluator beats every 20 s: one missed beat is not yet stale, two are.
    #[test]
    fn a_heartbeat_is_stale_after_two_missed_intervals() {
        let now = 1_000_000;
        assert!(!super::heartbeat_stale(60, Some(now - 20_000), now));
        assert!(!super::heartbeat_stale(60, Some(now - 40_000), now));
        assert!(super::heartbeat_stale(60, Some(now - 40_001), now));
        assert!(super::heartbeat_stale(60, None, now));
        // A lease of 0 s is read as 1 s: beats every 333 ms, stale after 666 ms.
        assert!(!super::heartbeat_stale(0, Some(now - 666), now));
        assert!(super::heartbeat_stale(0, Some(now - 667), now));
    }
}

#[cfg(test)]
mod build_tests {
    use dsrl_simulators::WorkerStatus;

    include!("../../suite/build-support/python_digest.rs");

    /// The digest baked at build time is the tree's package (build.rs re-runs when the package changes).
    #[test]
    fn the_baked_python_digest_is_the_trees() {
        let tree = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../sim/python/dsrl_sim");
        assert_eq!(python_package_digest(&tree).unwrap()[..12], *super::SIMULATOR_PYTHON);
    }

    /// The scorer's label is marked by a worker with other Python, and left as built by one with the build's
    /// (the marking itself: dsrl_simulators' python_package tests).
    #[test]
    fn a_worker_with_other_python_marks_the_scorer_build() {
        let worker = |version: &str| WorkerStatus {
            name: "w".into(),
            kind: "local".into(),
            address: None,
            pid: None,
            healthy: true,
            sessions: 0,
            envs: 0,
            max_envs: 32,
            version: Some(version.into()),
            restarts: 0,
            last_error: None,
        };
        let build = super::SCORER_BUILD;
        let ours = format!("dsrl-sim-worker 0.1.0 (dsrl_sim {})", super::SIMULATOR_PYTHON);
        assert_eq!(super::scorer_build(&[worker(&ours)]), build);
        let marked = super::scorer_build(&[worker("dsrl-sim-worker 0.1.0 (dsrl_sim 000000000000)")]);
        assert!(marked.ends_with("-modified)"), "{marked}");
    }

    /// A scoring-path file outside what build.rs watches would let a changed scorer report a clean commit.
    #[test]
    fn the_scorer_build_watches_the_scoring_path() {
        let build = include_str!("../build.rs");
        for entry in dsrl_evaluation::SCORING_PATH {
            let watched = match entry.strip_prefix("leaderboard/") {
                Some(own) => build.contains("\"src\"") && own.starts_with("src/"),
                None => build.contains(&format!("\"../{entry}\"")),
            };
            assert!(
                watched,
                "leaderboard/build.rs does not watch {entry}, which is on the scoring path"
            );
        }
        assert!(
            build.contains("\"../Cargo.lock\""),
            "the scoring dependencies' versions are in Cargo.lock"
        );
        assert!(
            build.contains("\"../Cargo.toml\""),
            "the scoring dependencies' features are declared in the workspace's Cargo.toml"
        );
    }
}
