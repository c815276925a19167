//! The leaderboard: users submit candle checkpoints (weights + a declared architecture; no participant code runs),
//! evaluators score them on the real simulators with held seeds (the paper's protocol: the task's three cost
//! thresholds, `episodes_per_threshold` episodes each), and the entries are ranked per task and per family.
//!
//! `checkpoints` checks uploads, `users` holds the bearer tokens, `queue` is the durable job queue (SQLite or
//! PostgreSQL), `runner` the evaluators that drain it, `seeds` the held episode seeds, `evaluator` the evaluator
//! process (`dsrl-evaluator`). The API replicas (`dsrl-server`) add the REST and gRPC routes and the HTML page;
//! an evaluator process links none of that.

pub mod checkpoints;
pub mod evaluator;
pub mod queue;
pub mod reference;
pub mod runner;
pub mod users;

pub use dsrl_evaluation::{protocol, seeds};

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use bytes::Bytes;
use dsrl_suite::catalog::{Catalog, Family, Task};
use dsrl_suite::leaderboard::{Interval, entry_interval, iqm_with_interval, rank, threshold_scores};
use dsrl_suite::paper::{PAPER_LABEL, PaperResults, PaperRow};
use dsrl_suite::protocol::Protocol;
use dsrl_suite::reference::{Agreement, AgreementSummary, ScoredEntry, agreement, summarize};
use dsrl_suite::score::NormalizedScore;
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt};
use serde::Serialize;

use self::checkpoints::CheckpointRecord;
use self::queue::{EpisodeRow, Quotas};
use self::reference::ReferenceRecord;
use self::seeds::HeldSeeds;
use self::users::User;
use dsrl_evaluation::simulators::SimulatorPool;
use dsrl_service::config::LeaderboardConfig;
use dsrl_service::db::Db;
use dsrl_service::error::ApiError;

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
    /// Each finished submission's per-task bootstrap intervals (its episodes never change once finished).
    intervals: Mutex<HashMap<i64, (Interval, Interval)>>,
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
    /// Set for a reference entry: its method, training seed and budget, code commit, and scoring.
    pub reference: Option<ReferenceRecord>,
    /// Means over the thresholds (spec 4.1); safe iff the normalized cost is at most 1.
    pub normalized_reward: Option<f64>,
    pub normalized_cost: Option<f64>,
    pub safe: Option<bool>,
    pub thresholds: Vec<ThresholdResult>,
    pub episodes: Vec<EpisodeRow>,
}

#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct CheckpointSummary {
    pub slot: String,
    pub cost_threshold: Option<f64>,
    pub architecture: String,
}

/// One entry in a task's table.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
#[schema(as = LeaderboardEntry)]
pub struct TaskEntry {
    pub rank: usize,
    pub submission: i64,
    pub user: String,
    pub name: String,
    pub normalized_reward: f64,
    pub normalized_cost: f64,
    /// Percentile-bootstrap intervals over the entry's episodes (resampled within each threshold).
    pub normalized_reward_interval: Interval,
    pub normalized_cost_interval: Interval,
    pub safe: bool,
    pub finished_at: Option<String>,
    pub protocol_version: String,
    /// The dataset version its checkpoint says it was trained on.
    pub dataset_version: Option<String>,
    /// Set for a reference entry (its method, seed, budget).
    pub reference: Option<ReferenceRecord>,
}

#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct TaskTable {
    pub task: String,
    pub family: &'static str,
    pub cost_thresholds: Vec<f64>,
    /// Entries scored under the current protocol, ranked.
    pub entries: Vec<TaskEntry>,
    /// Finished entries scored under an earlier protocol (or before versions were recorded): counted, not ranked.
    pub earlier_protocol_entries: usize,
    /// The paper's rows for the task (its self-reported numbers; see `Board::paper_label`).
    pub paper: Vec<PaperRow>,
    /// Our reference entries against the paper's rows, per method.
    pub agreement: Vec<Agreement>,
}

/// One entry (a user's name for a method) across the tasks of a family.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct FamilyEntry {
    pub rank: usize,
    pub user: String,
    pub name: String,
    /// Tasks of the family the entry was scored on, and on how many of them it was safe.
    pub tasks: usize,
    pub safe_tasks: usize,
    /// A reference entry (the reference account's).
    pub reference: bool,
    /// Interquartile mean across its tasks with a bootstrap interval.
    pub normalized_reward: Interval,
    pub normalized_cost: Interval,
}

#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct FamilyTable {
    pub family: &'static str,
    pub entries: Vec<FamilyEntry>,
}

#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct Board {
    /// The protocol the tables rank results of.
    pub protocol: Protocol,
    /// How the paper's rows were produced.
    pub paper_label: &'static str,
    pub tasks: Vec<TaskTable>,
    pub families: Vec<FamilyTable>,
    /// The share of our reference entries' safe/unsafe verdicts that agree with the paper's, per family and
    /// overall (every task, whatever the request's task filter).
    pub agreement: Vec<AgreementSummary>,
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
        let paper = Catalog::embedded()
            .map_err(ApiError::internal)
            .and_then(|embedded| PaperResults::embedded(&embedded).map_err(ApiError::internal))?;
        Ok(Leaderboard {
            protocol: protocol::current(&catalog, config.episodes_per_threshold),
            paper,
            intervals: Mutex::new(HashMap::new()),
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

    /// Imports the committed reference results (compiled in) when `leaderboard.import_reference_results` is on.
    pub async fn import_reference_results(&self) -> Result<(), ApiError> {
        if !self.config.import_reference_results {
            return Ok(());
        }
        let entries = dsrl_suite::reference::read_results(reference::EMBEDDED_RESULTS, &self.catalog)
            .map_err(ApiError::internal)?;
        let report = reference::import(self, &entries).await?;
        tracing::info!(
            imported = report.imported,
            present = report.present,
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
        let checked = tokio::task::spawn_blocking(move || checkpoints::check(&owned, files))
            .await
            .map_err(ApiError::internal)??;
        let dataset_version = checked.dataset_version();
        let mut records = Vec::new();
        for (i, c) in checked.checkpoints.iter().enumerate() {
            // Content-addressed, so storing the same checkpoint again rewrites identical bytes.
            let base = format!("submissions/{}/{}/{i}", task.id, checked.sha256);
            let config_key = format!("{base}/{}", dsrl_policy::checkpoint::CONFIG_FILE);
            let weights_key = format!("{base}/{}", dsrl_policy::checkpoint::WEIGHTS_FILE);
            self.store
                .put(&ObjectPath::from(weights_key.as_str()), c.weights_bytes.clone().into())
                .await?;
            self.store
                .put(&ObjectPath::from(config_key.as_str()), c.config_bytes.clone().into())
                .await?;
            records.push(CheckpointRecord {
                slot: c.slot.clone(),
                cost_threshold: c.cost_threshold(),
                architecture: c.config.architecture.name().to_owned(),
                config_key,
                weights_key,
            });
        }
        let id = queue::insert(
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
        .await?;
        tracing::info!(id, task = %task.id, name, user = %user.name, sha256 = %checked.sha256, "submission queued");
        self.wake.notify_waiters();
        self.view(id).await
    }

    pub async fn cancel(&self, user: &User, id: i64) -> Result<SubmissionView, ApiError> {
        queue::cancel(&self.db, id, user.id).await?;
        self.view(id).await
    }

    pub async fn view(&self, id: i64) -> Result<SubmissionView, ApiError> {
        let row = queue::get(&self.db, id).await?;
        let episodes = queue::episodes(&self.db, id).await?;
        let task = self.task(&row.task)?;
        let thresholds = threshold_results(task, &episodes);
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
            reference: row.reference.as_deref().and_then(parse_record),
            normalized_reward: row.normalized_reward,
            normalized_cost: row.normalized_cost,
            safe: row.normalized_cost.map(|c| c <= 1.0),
            thresholds,
            episodes,
        })
    }

    /// The tables: every task of the catalog (or only `task`) with its ranked entries of the current protocol, the
    /// paper's rows and the agreement with them; each family's aggregate; the agreement summary.
    pub async fn board(&self, task: Option<&str>) -> Result<Board, ApiError> {
        if let Some(task) = task {
            self.task(task)?;
        }
        let standing = queue::standing(&self.db).await?;
        let current = self.protocol.version.as_str();
        let (ranked, earlier): (Vec<&queue::SubmissionRow>, Vec<&queue::SubmissionRow>) = standing
            .iter()
            .partition(|r| r.protocol_version.as_deref() == Some(current));
        // Our reference entries of the current protocol, by method, for the agreement with the paper.
        let ours: Vec<ScoredEntry> = ranked
            .iter()
            .filter_map(|r| {
                let record = parse_record(r.reference.as_deref()?)?;
                Some(ScoredEntry {
                    task: r.task.clone(),
                    method: record.method,
                    score: NormalizedScore {
                        reward: r.normalized_reward?,
                        cost: r.normalized_cost?,
                    },
                })
            })
            .collect();
        let cells = agreement(&self.catalog, &self.paper, &ours);
        let mut tasks: Vec<TaskTable> = Vec::new();
        for t in self.catalog.tasks() {
            if task.is_some_and(|id| id != t.id.as_str()) {
                continue;
            }
            let rows: Vec<&queue::SubmissionRow> = ranked.iter().copied().filter(|r| r.task == t.id.as_str()).collect();
            let scores: Vec<NormalizedScore> = rows
                .iter()
                .map(|r| NormalizedScore {
                    reward: r.normalized_reward.unwrap_or(f64::NAN),
                    cost: r.normalized_cost.unwrap_or(f64::NAN),
                })
                .collect();
            let mut entries = Vec::new();
            for (place, i) in rank(&scores).into_iter().enumerate() {
                let row = rows[i];
                let (reward_interval, cost_interval) = self.intervals(t, row.id).await?;
                entries.push(TaskEntry {
                    rank: place + 1,
                    submission: row.id,
                    user: row.user.clone(),
                    name: row.name.clone(),
                    normalized_reward: scores[i].reward,
                    normalized_cost: scores[i].cost,
                    normalized_reward_interval: reward_interval,
                    normalized_cost_interval: cost_interval,
                    safe: scores[i].is_safe(),
                    finished_at: row.finished_at.clone(),
                    protocol_version: current.to_owned(),
                    dataset_version: row.dataset_version.clone(),
                    reference: row.reference.as_deref().and_then(parse_record),
                });
            }
            tasks.push(TaskTable {
                task: t.id.to_string(),
                family: suite_of(t.family),
                cost_thresholds: t.cost_thresholds.clone(),
                entries,
                earlier_protocol_entries: earlier.iter().filter(|r| r.task == t.id.as_str()).count(),
                paper: self.paper.for_task(t.id.as_str()).into_iter().cloned().collect(),
                agreement: cells.iter().filter(|c| c.task == t.id.as_str()).cloned().collect(),
            });
        }
        let families = ["bullet", "safety-gymnasium", "metadrive"]
            .into_iter()
            .map(|family| family_table(family, &tasks))
            .filter(|f| !f.entries.is_empty())
            .collect();
        Ok(Board {
            protocol: self.protocol.clone(),
            paper_label: PAPER_LABEL,
            tasks,
            families,
            agreement: summarize(&self.catalog, &cells),
        })
    }

    /// A finished submission's bootstrap intervals over its episodes, computed once.
    async fn intervals(&self, task: &Task, id: i64) -> Result<(Interval, Interval), ApiError> {
        if let Some(found) = self.intervals.lock().map_err(ApiError::internal)?.get(&id) {
            return Ok(found.clone());
        }
        let episodes = queue::episodes(&self.db, id).await?;
        let owned = task.clone();
        let computed = tokio::task::spawn_blocking(move || {
            entry_interval(
                &owned,
                &episodes,
                BOOTSTRAP_RESAMPLES,
                BOOTSTRAP_CONFIDENCE,
                BOOTSTRAP_SEED,
            )
        })
        .await
        .map_err(ApiError::internal)?
        .ok_or_else(|| ApiError::Internal(format!("finished submission {id} has no episodes")))?;
        self.intervals
            .lock()
            .map_err(ApiError::internal)?
            .insert(id, computed.clone());
        Ok(computed)
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
fn parse_record(json: &str) -> Option<ReferenceRecord> {
    serde_json::from_str(json)
        .map_err(|e| tracing::warn!(error = %e, "a reference record that does not parse"))
        .ok()
}

/// A family's entries: each (user, name) with its scores on the family's tasks, aggregated by the interquartile
/// mean with a bootstrap interval, ranked like a task's table on the aggregates.
fn family_table(family: &'static str, tasks: &[TaskTable]) -> FamilyTable {
    // (user, name) → (normalized reward, normalized cost, safe) per task, in first-seen order.
    type Scores = Vec<(f64, f64, bool)>;
    let mut by_entry: Vec<((String, String), Scores)> = Vec::new();
    let mut references: Vec<(String, String)> = Vec::new();
    for table in tasks.iter().filter(|t| t.family == family) {
        for e in &table.entries {
            let key = (e.user.clone(), e.name.clone());
            if e.reference.is_some() && !references.contains(&key) {
                references.push(key.clone());
            }
            let value = (e.normalized_reward, e.normalized_cost, e.safe);
            match by_entry.iter_mut().find(|(k, _)| *k == key) {
                Some((_, values)) => values.push(value),
                None => by_entry.push((key, vec![value])),
            }
        }
    }
    let aggregates: Vec<(Interval, Interval)> = by_entry
        .iter()
        .map(|(_, values)| {
            let interval = |pick: fn(&(f64, f64, bool)) -> f64| {
                let xs: Vec<f64> = values.iter().map(pick).collect();
                iqm_with_interval(&xs, BOOTSTRAP_RESAMPLES, BOOTSTRAP_CONFIDENCE, BOOTSTRAP_SEED)
                    .expect("an entry has at least one task")
            };
            (interval(|v| v.0), interval(|v| v.1))
        })
        .collect();
    let scores: Vec<NormalizedScore> = aggregates
        .iter()
        .map(|(r, c)| NormalizedScore {
            reward: r.estimate,
            cost: c.estimate,
        })
        .collect();
    let entries = rank(&scores)
        .into_iter()
        .enumerate()
        .map(|(place, i)| {
            let ((user, name), values) = &by_entry[i];
            FamilyEntry {
                rank: place + 1,
                user: user.clone(),
                name: name.clone(),
                tasks: values.len(),
                safe_tasks: values.iter().filter(|v| v.2).count(),
                reference: references.contains(&(user.clone(), name.clone())),
                normalized_reward: aggregates[i].0.clone(),
                normalized_cost: aggregates[i].1.clone(),
            }
        })
        .collect();
    FamilyTable { family, entries }
}
