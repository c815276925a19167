//! The tables of the leaderboard: each task's ranked entries of the current protocol (a reference method's training
//! seeds as one row, with an interval over seeds and episodes), the paper's and published rows beside them, the
//! agreement of our reference entries with the paper's verdicts, and each family's aggregate over the entries
//! scored on all its tasks. `Leaderboard::board` assembles them from the queue's standing rows.

use dsrl_scoring::leaderboard::{Interval, entry_interval, iqm_over_seeds_with_interval, rank, seeds_interval};
use dsrl_scoring::paper::{PAPER_LABEL, PaperRow};
use dsrl_scoring::protocol::Protocol;
use dsrl_scoring::published::PublishedRow;
use dsrl_scoring::reference::{Agreement, AgreementSummary, ScoredEntry, agreement, summarize, summarize_by_method};
use dsrl_suite::catalog::Task;
use dsrl_suite::score::NormalizedScore;
use serde::Serialize;

use crate::queue;
use crate::reference::{ReferenceRecord, TrainingData};
use crate::{BOOTSTRAP_CONFIDENCE, BOOTSTRAP_RESAMPLES, BOOTSTRAP_SEED, Leaderboard, parse_record, suite_of};
use dsrl_service::error::ApiError;

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
    /// Submissions its author has made to this task, whatever became of them: a best of many tries shows as one.
    pub author_submissions_to_task: u32,
    /// Percentile-bootstrap intervals: over the entry's episodes (resampled within each threshold), or, for a
    /// method's several training seeds, over seeds and then episodes within each (`interval_covers` says which).
    pub normalized_reward_interval: Interval,
    pub normalized_cost_interval: Interval,
    /// What the intervals resample: `episodes` (one training seed: episode variance only) or `training seeds and
    /// episodes`.
    pub interval_covers: String,
    /// For a method's several training seeds shown as one row (the mean over them, ranked by it): each seed's
    /// entry, reachable at `/submissions/{submission}`. Empty for a single entry.
    pub training_seeds: Vec<SeedRun>,
    pub safe: bool,
    pub finished_at: Option<String>,
    pub protocol_version: String,
    /// The dataset version its checkpoint says it was trained on.
    pub dataset_version: Option<String>,
    /// The build that scored it, where recorded.
    pub scored_by: Option<String>,
    /// Set for a reference entry (its method, seed, budget).
    pub reference: Option<ReferenceRecord>,
}

/// One training seed of a reference entry shown with its method's other seeds.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct SeedRun {
    pub submission: i64,
    pub seed: u64,
    pub normalized_reward: f64,
    pub normalized_cost: f64,
    pub safe: bool,
}

/// What a one-seed entry's intervals resample.
pub const EPISODES_ONLY: &str = "episodes";
/// What the intervals of a method's several seeds resample.
pub const SEEDS_AND_EPISODES: &str = "training seeds and episodes";

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
    /// Rows methods beyond the paper publish for the task, each with its citation and protocol: self-reported,
    /// not comparable cell for cell (FISOR's use one cost limit), and never part of the agreement.
    pub published: Vec<PublishedRow>,
    /// Our starter-trained reference entries against the paper's rows, per method.
    pub agreement: Vec<Agreement>,
    /// The same for our entries trained on the task's full build.
    pub full_build_agreement: Vec<Agreement>,
}

/// One entry across the tasks of a family: a user's name for a method, or a reference method with its training
/// seeds together.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct FamilyEntry {
    /// Its place among the entries scored on every task of the family; `None` for a partial entry (listed apart:
    /// an aggregate over fewer tasks is not comparable).
    pub rank: Option<usize>,
    pub user: String,
    pub name: String,
    /// Tasks of the family the entry was scored on, and on how many of them it was safe.
    pub tasks: usize,
    pub safe_tasks: usize,
    /// The most training seeds it has on one task (1 for a submission).
    pub training_seeds: usize,
    /// A reference entry (the reference account's).
    pub reference: bool,
    /// Interquartile mean across its tasks (each task's mean over training seeds) with a bootstrap interval that
    /// resamples tasks and then, within each, training seeds.
    pub normalized_reward: Interval,
    pub normalized_cost: Interval,
}

#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct FamilyTable {
    pub family: &'static str,
    /// Tasks in the family: an entry is ranked when it was scored on all of them.
    pub tasks: usize,
    /// Entries scored on every task of the family, ranked on their aggregates.
    pub entries: Vec<FamilyEntry>,
    /// Entries scored on some of its tasks, most tasks first: shown with their coverage, not ranked.
    pub partial: Vec<FamilyEntry>,
}

#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct Board {
    /// The protocol the tables rank results of.
    pub protocol: Protocol,
    /// How the paper's rows were produced.
    pub paper_label: &'static str,
    pub tasks: Vec<TaskTable>,
    pub families: Vec<FamilyTable>,
    /// The share of our starter-trained reference entries' safe/unsafe verdicts that agree with the paper's, per
    /// family and overall (every task, whatever the request's task filter), each with what trivial rules would agree on.
    pub agreement: Vec<AgreementSummary>,
    /// The same per method (`scope` is the method), over every task.
    pub agreement_by_method: Vec<AgreementSummary>,
    /// `agreement` for the reference entries trained on the full builds, over the cells they cover: never mixed
    /// with the starter-trained entries' (which `agreement` counts alone).
    pub full_build_agreement: Vec<AgreementSummary>,
    pub full_build_agreement_by_method: Vec<AgreementSummary>,
}

impl Leaderboard {
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
        // Entries trained on the starters and on the full builds are measured apart: the data differ, and mixing
        // them would credit one with the other's verdicts.
        let (mut starter, mut full_build) = (Vec::new(), Vec::new());
        for r in &ranked {
            let Some(record) = r.reference.as_deref().and_then(parse_record) else {
                continue;
            };
            let (Some(reward), Some(cost)) = (r.normalized_reward, r.normalized_cost) else {
                continue;
            };
            let ours = match record.dataset {
                TrainingData::Starter => &mut starter,
                TrainingData::FullBuild => &mut full_build,
            };
            ours.push(ScoredEntry {
                task: r.task.clone(),
                method: record.method,
                score: NormalizedScore { reward, cost },
            });
        }
        let cells = agreement(&self.catalog, &self.paper, &starter);
        let full_build_cells = agreement(&self.catalog, &self.paper, &full_build);
        let counts = queue::submission_counts(&self.db).await?;
        let mut tasks: Vec<TaskTable> = Vec::new();
        for t in self.catalog.tasks() {
            if task.is_some_and(|id| id != t.id.as_str()) {
                continue;
            }
            let rows: Vec<&queue::SubmissionRow> = ranked.iter().copied().filter(|r| r.task == t.id.as_str()).collect();
            // One row per entry; a reference method's training seeds (same budget, same dataset) are one row, the
            // mean over them, ranked by it.
            let groups = seed_groups(&rows);
            let score_of = |r: &queue::SubmissionRow| NormalizedScore {
                reward: r.normalized_reward.unwrap_or(f64::NAN),
                cost: r.normalized_cost.unwrap_or(f64::NAN),
            };
            let scores: Vec<NormalizedScore> = groups
                .iter()
                .map(|members| dsrl_scoring::reference::mean_over_seeds(members.iter().map(|(row, _)| score_of(row))))
                .collect();
            let mut entries = Vec::new();
            for (place, i) in rank(&scores).into_iter().enumerate() {
                let members = &groups[i];
                let (row, record) = &members[0];
                let (name, (reward_interval, cost_interval), covers, training_seeds) = if members.len() == 1 {
                    (
                        row.name.clone(),
                        self.intervals(t, vec![row.id]).await?,
                        EPISODES_ONLY,
                        Vec::new(),
                    )
                } else {
                    let ids: Vec<i64> = members.iter().map(|(r, _)| r.id).collect();
                    let record = record.as_ref().expect("only reference entries are grouped");
                    let seeds: Vec<String> = members
                        .iter()
                        .filter_map(|(_, r)| r.as_ref().map(|r| r.seed.to_string()))
                        .collect();
                    let runs = members
                        .iter()
                        .map(|(r, rec)| {
                            let score = score_of(r);
                            SeedRun {
                                submission: r.id,
                                seed: rec.as_ref().map_or(0, |rec| rec.seed),
                                normalized_reward: score.reward,
                                normalized_cost: score.cost,
                                safe: score.is_safe(),
                            }
                        })
                        .collect();
                    (
                        format!("{} (seeds {})", record.label(), seeds.join(", ")),
                        self.intervals(t, ids).await?,
                        SEEDS_AND_EPISODES,
                        runs,
                    )
                };
                entries.push(TaskEntry {
                    rank: place + 1,
                    submission: row.id,
                    user: row.user.clone(),
                    name,
                    normalized_reward: scores[i].reward,
                    normalized_cost: scores[i].cost,
                    author_submissions_to_task: counts.get(&(row.user_id, row.task.clone())).copied().unwrap_or(1),
                    normalized_reward_interval: reward_interval,
                    normalized_cost_interval: cost_interval,
                    interval_covers: covers.to_owned(),
                    training_seeds,
                    safe: scores[i].is_safe(),
                    finished_at: row.finished_at.clone(),
                    protocol_version: current.to_owned(),
                    dataset_version: row.dataset_version.clone(),
                    scored_by: row.scored_by.clone(),
                    reference: record.clone(),
                });
            }
            tasks.push(TaskTable {
                task: t.id.to_string(),
                family: suite_of(t.family),
                cost_thresholds: t.cost_thresholds.clone(),
                entries,
                earlier_protocol_entries: earlier.iter().filter(|r| r.task == t.id.as_str()).count(),
                paper: self.paper.for_task(t.id.as_str()).into_iter().cloned().collect(),
                published: self.published.for_task(t.id.as_str()).into_iter().cloned().collect(),
                agreement: cells.iter().filter(|c| c.task == t.id.as_str()).cloned().collect(),
                full_build_agreement: full_build_cells
                    .iter()
                    .filter(|c| c.task == t.id.as_str())
                    .cloned()
                    .collect(),
            });
        }
        let families = ["bullet", "safety-gymnasium", "metadrive"]
            .into_iter()
            .map(|family| family_table(family, &tasks))
            .filter(|f| !f.entries.is_empty() || !f.partial.is_empty())
            .collect();
        Ok(Board {
            protocol: self.protocol.clone(),
            paper_label: PAPER_LABEL,
            tasks,
            families,
            agreement: summarize(&self.catalog, &cells),
            agreement_by_method: summarize_by_method(&cells),
            full_build_agreement: summarize(&self.catalog, &full_build_cells),
            full_build_agreement_by_method: summarize_by_method(&full_build_cells),
        })
    }

    /// The bootstrap intervals of one finished submission (`ids` = its id: over its episodes) or of a method's
    /// training seeds (their submissions: over the seeds, then each seed's episodes, `seeds_interval`), computed
    /// once: a finished submission's episodes never change.
    async fn intervals(&self, task: &Task, ids: Vec<i64>) -> Result<(Interval, Interval), ApiError> {
        if let Some(found) = self.intervals.lock().map_err(ApiError::internal)?.get(&ids) {
            return Ok(found.clone());
        }
        let mut seeds = Vec::with_capacity(ids.len());
        for &id in &ids {
            seeds.push(queue::episodes(&self.db, id).await?);
        }
        let owned = task.clone();
        let computed = tokio::task::spawn_blocking(move || {
            let (n, confidence, seed) = (BOOTSTRAP_RESAMPLES, BOOTSTRAP_CONFIDENCE, BOOTSTRAP_SEED);
            match seeds.as_slice() {
                [episodes] => entry_interval(&owned, episodes, n, confidence, seed),
                _ => seeds_interval(&owned, &seeds, n, confidence, seed),
            }
        })
        .await
        .map_err(ApiError::internal)?
        .ok_or_else(|| ApiError::Internal(format!("finished submissions {ids:?}: one has no episodes")))?;
        self.intervals
            .lock()
            .map_err(ApiError::internal)?
            .insert(ids, computed.clone());
        Ok(computed)
    }
}

/// A submission on a task's table with its parsed reference record.
type Member<'a> = (&'a queue::SubmissionRow, Option<ReferenceRecord>);

/// A task's rows, in submission order: each reference entry grouped with the other training seeds of its method,
/// budget and dataset (sorted by seed), every other entry alone. Each member comes with its parsed reference record.
fn seed_groups<'a>(rows: &[&'a queue::SubmissionRow]) -> Vec<Vec<Member<'a>>> {
    // (user, method, steps, batch size, dataset version).
    type Key = (String, String, u64, usize, Option<String>);
    let mut groups: Vec<(Option<Key>, Vec<Member>)> = Vec::new();
    for &row in rows {
        let record = row.reference.as_deref().and_then(parse_record);
        let key = record.as_ref().map(|r| {
            (
                row.user.clone(),
                r.method.clone(),
                r.training.steps,
                r.training.batch_size,
                row.dataset_version.clone(),
            )
        });
        match groups.iter_mut().find(|(k, _)| k.is_some() && *k == key) {
            Some((_, members)) => members.push((row, record)),
            None => groups.push((key, vec![(row, record)])),
        }
    }
    groups
        .into_iter()
        .map(|(_, mut members)| {
            members.sort_by_key(|(_, r)| r.as_ref().map_or(0, |r| r.seed));
            members
        })
        .collect()
}

/// A family's entries: per (user, entry) — a reference method with its training seeds together, or a user's name —
/// its scores on the family's tasks (per task, each seed's), aggregated by the interquartile mean over tasks of the
/// per-task means over seeds, with a bootstrap interval that resamples tasks and then seeds within each. Only
/// entries scored on every task of the family are ranked (like a task's table, on the aggregates); the others are
/// listed apart with their coverage.
fn family_table(family: &'static str, tasks: &[TaskTable]) -> FamilyTable {
    // (user, entry) → per task: each seed's (normalized reward, normalized cost), and the task's verdict.
    type Scores = Vec<(Vec<(f64, f64)>, bool)>;
    let mut by_entry: Vec<((String, String), Scores)> = Vec::new();
    let mut references: Vec<(String, String)> = Vec::new();
    let family_tasks = tasks.iter().filter(|t| t.family == family).count();
    for table in tasks.iter().filter(|t| t.family == family) {
        for e in &table.entries {
            let name = match &e.reference {
                Some(record) => record.label(),
                None => e.name.clone(),
            };
            let key = (e.user.clone(), name);
            if e.reference.is_some() && !references.contains(&key) {
                references.push(key.clone());
            }
            let seeds = if e.training_seeds.is_empty() {
                vec![(e.normalized_reward, e.normalized_cost)]
            } else {
                e.training_seeds
                    .iter()
                    .map(|s| (s.normalized_reward, s.normalized_cost))
                    .collect()
            };
            match by_entry.iter_mut().find(|(k, _)| *k == key) {
                Some((_, values)) => values.push((seeds, e.safe)),
                None => by_entry.push((key, vec![(seeds, e.safe)])),
            }
        }
    }
    let aggregates: Vec<(Interval, Interval)> = by_entry
        .iter()
        .map(|(_, values)| {
            let per_task = |pick: fn(&(f64, f64)) -> f64| -> Vec<Vec<f64>> {
                values
                    .iter()
                    .map(|(seeds, _)| seeds.iter().map(pick).collect())
                    .collect()
            };
            (
                iqm_over_seeds_with_interval(
                    &per_task(|v| v.0),
                    BOOTSTRAP_RESAMPLES,
                    BOOTSTRAP_CONFIDENCE,
                    BOOTSTRAP_SEED,
                ),
                iqm_over_seeds_with_interval(
                    &per_task(|v| v.1),
                    BOOTSTRAP_RESAMPLES,
                    BOOTSTRAP_CONFIDENCE,
                    BOOTSTRAP_SEED,
                ),
            )
        })
        .collect();
    let entry = |i: usize, rank: Option<usize>| {
        let ((user, name), values) = &by_entry[i];
        FamilyEntry {
            rank,
            user: user.clone(),
            name: name.clone(),
            tasks: values.len(),
            safe_tasks: values.iter().filter(|v| v.1).count(),
            training_seeds: values.iter().map(|v| v.0.len()).max().unwrap_or(1),
            reference: references.contains(&(user.clone(), name.clone())),
            normalized_reward: aggregates[i].0.clone(),
            normalized_cost: aggregates[i].1.clone(),
        }
    };
    let (complete, partial): (Vec<usize>, Vec<usize>) =
        (0..by_entry.len()).partition(|&i| by_entry[i].1.len() == family_tasks);
    let scores: Vec<NormalizedScore> = complete
        .iter()
        .map(|&i| NormalizedScore {
            reward: aggregates[i].0.estimate,
            cost: aggregates[i].1.estimate,
        })
        .collect();
    let entries = rank(&scores)
        .into_iter()
        .enumerate()
        .map(|(place, j)| entry(complete[j], Some(place + 1)))
        .collect();
    let mut partial: Vec<FamilyEntry> = partial.into_iter().map(|i| entry(i, None)).collect();
    partial.sort_by_key(|e| std::cmp::Reverse(e.tasks));
    FamilyTable {
        family,
        tasks: family_tasks,
        entries,
        partial,
    }
}
