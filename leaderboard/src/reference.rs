//! The reference entries on every server: the committed results files (`data/reference/results.jsonl`, the entries
//! trained on the starters, and `data/reference/full_builds.jsonl`, those trained on the full builds; compiled in)
//! imported at start-up as finished submissions of the reference account, each with its record (method, seed,
//! training budget, dataset version, code commit, how it was scored) and every episode. Importing, not re-scoring:
//! a fresh server shows them at once, the larger checkpoints need not be in the repository, and each entry keeps
//! the protocol version it was scored under, so an entry from another protocol is counted, not ranked (see
//! docs/leaderboard.md, "The leaderboard of record"). Idempotent: an entry already present is left alone (its record
//! brought up to the file's when only that changed, as when its checkpoints were reproduced by another commit), and the
//! reference account's entries that the file no longer holds are withdrawn (kept, off the tables).

use serde::{Deserialize, Serialize};

use dsrl_scoring::reference::{ReferenceEntry, ScoringRecord, TrainingBudget};
use dsrl_service::error::ApiError;

use super::Leaderboard;
use super::queue::{self, Imported, Scores};
use super::users;

/// `data/reference/results.jsonl`, compiled in (here, not in the suite, so a new results file rebuilds only the
/// leaderboard and what links it): what a fresh server imports.
pub const EMBEDDED_RESULTS: &str = include_str!("../../data/reference/results.jsonl");

/// `data/reference/full_builds.jsonl`, compiled in: the entries trained on the tasks' full builds. They are shown
/// beside the starter-trained ones, never mixed with them: apart in the tables, and in an agreement of their own.
pub const EMBEDDED_FULL_BUILD_RESULTS: &str = include_str!("../../data/reference/full_builds.jsonl");

/// Which kind of hosted dataset a reference entry was trained on (its `dataset_version` names the exact bytes).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum TrainingData {
    /// The committed starter (`data/starters/`): a cut of the full build, what a default server hosts. Records
    /// written before the full builds existed carry no kind, and were all trained on starters.
    #[default]
    Starter,
    /// The task's paper-size full build (`data/full/`).
    FullBuild,
}

impl TrainingData {
    pub fn as_str(self) -> &'static str {
        match self {
            TrainingData::Starter => "starter",
            TrainingData::FullBuild => "full build",
        }
    }
}

/// What a reference entry's row records beside the scores (the `reference` column, JSON), as the tables show it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ReferenceRecord {
    pub method: String,
    pub seed: u64,
    pub training: TrainingBudget,
    pub code_commit: String,
    pub scoring: ScoringRecord,
    /// The kind of dataset it was trained on.
    #[serde(default)]
    pub dataset: TrainingData,
}

impl ReferenceRecord {
    /// The entry's method as the tables name it: the method alone for a starter-trained entry, marked for one
    /// trained on a full build, so that the two never share a row or an aggregate.
    pub fn label(&self) -> String {
        method_label(&self.method, self.dataset)
    }
}

/// A method's name on the tables for entries trained on `dataset`.
pub fn method_label(method: &str, dataset: TrainingData) -> String {
    match dataset {
        TrainingData::Starter => method.to_owned(),
        TrainingData::FullBuild => format!("{method} [full build]"),
    }
}

/// An entry's name on the tables: the method (marked when trained on a full build) and its training seed.
pub fn entry_name(method: &str, seed: u64, dataset: TrainingData) -> String {
    format!("{} (seed {seed})", method_label(method, dataset))
}

/// What an import did.
#[derive(Debug, Default, Clone, PartialEq, Serialize)]
pub struct ImportReport {
    pub imported: usize,
    pub present: usize,
    /// Entries present with the same scoring whose record (training, code commit) the file has changed.
    pub updated: usize,
    /// Entries whose checkpoint a user's live submission already holds on this server.
    pub held_by_submissions: usize,
    pub withdrawn: u64,
}

/// Imports `entries`, each with the kind of dataset it was trained on (checked against the catalog by
/// `read_results`); the reference account's entries not among them are withdrawn.
pub async fn import(
    leaderboard: &Leaderboard,
    entries: &[(TrainingData, ReferenceEntry)],
) -> Result<ImportReport, ApiError> {
    let db = &leaderboard.db;
    let user = users::reference_user(db).await?;
    let mut report = ImportReport::default();
    for (dataset, entry) in entries {
        let task = leaderboard.task(&entry.task)?;
        let Some(score) = entry.score(task) else { continue };
        let existing = sqlx::query(sqlx::AssertSqlSafe(format!(
            "SELECT id, user_id, protocol_version, finished_at, reference FROM submissions
             WHERE task = $1 AND checkpoint_sha256 = $2 AND {}",
            queue::HOLDS_CHECKPOINT
        )))
        .bind(&entry.task)
        .bind(&entry.checkpoint_sha256)
        .fetch_optional(db.pool())
        .await?;
        let record = ReferenceRecord {
            method: entry.method.clone(),
            seed: entry.seed,
            training: entry.training.clone(),
            code_commit: entry.code_commit.clone(),
            scoring: entry.scoring.clone(),
            dataset: *dataset,
        };
        let record = serde_json::to_string(&record).map_err(ApiError::internal)?;
        if let Some(row) = existing {
            use sqlx::Row;
            let (id, owner): (i64, i64) = (row.try_get(0)?, row.try_get(1)?);
            let (protocol, finished): (Option<String>, Option<String>) = (row.try_get(2)?, row.try_get(3)?);
            if owner != user {
                report.held_by_submissions += 1;
                continue;
            }
            if protocol.as_deref() == Some(entry.protocol_version.as_str())
                && finished.as_deref() == Some(entry.scoring.finished_at.as_str())
            {
                let stored: Option<String> = row.try_get(4)?;
                if stored.as_deref() == Some(record.as_str()) {
                    report.present += 1;
                } else {
                    queue::set_reference(db, id, &record).await?;
                    report.updated += 1;
                }
                continue;
            }
            // The same checkpoint scored again (under another protocol, say): the new scoring replaces the old.
            queue::withdraw(
                db,
                id,
                "replaced by a later scoring of the same checkpoint in the reference results",
            )
            .await?;
        }
        let thresholds = task.cost_thresholds.len().max(1);
        let stored = queue::insert_finished(
            db,
            &Imported {
                user_id: user,
                task: &entry.task,
                name: &entry_name(&entry.method, entry.seed, *dataset),
                checkpoint_sha256: &entry.checkpoint_sha256,
                started_at: &entry.scoring.started_at,
                finished_at: &entry.scoring.finished_at,
                episodes_per_threshold: (entry.episodes.len() / thresholds) as u32,
                dataset_version: &entry.dataset_version,
                reference: &record,
                scored_by: entry.scoring.build.as_deref(),
                result: Scores {
                    episodes: &entry.episodes,
                    normalized_reward: score.reward,
                    normalized_cost: score.cost,
                    protocol_version: &entry.protocol_version,
                },
            },
        )
        .await?;
        if stored {
            report.imported += 1;
        } else {
            report.held_by_submissions += 1;
        }
    }
    let keep: Vec<(String, String)> = entries
        .iter()
        .map(|(_, e)| (e.task.clone(), e.checkpoint_sha256.clone()))
        .collect();
    report.withdrawn = queue::withdraw_except(
        db,
        user,
        &keep,
        "withdrawn: no longer in the committed reference results",
    )
    .await?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_record_without_a_dataset_kind_is_a_starters_and_the_kinds_never_share_a_name() {
        // A record as servers stored it before the kinds existed: the committed file's first entry, no `dataset`.
        let entry: serde_json::Value = serde_json::from_str(EMBEDDED_RESULTS.lines().next().unwrap()).unwrap();
        let record = serde_json::json!({
            "method": "BC-Safe",
            "seed": 1,
            "training": entry["training"],
            "code_commit": entry["code_commit"],
            "scoring": entry["scoring"],
        });
        let mut parsed: ReferenceRecord = serde_json::from_value(record).unwrap();
        assert_eq!(parsed.dataset, TrainingData::Starter);
        assert_eq!(parsed.label(), "BC-Safe");
        parsed.dataset = TrainingData::FullBuild;
        assert_eq!(parsed.label(), "BC-Safe [full build]");
        assert_eq!(serde_json::to_value(&parsed).unwrap()["dataset"], "full_build");
        assert_ne!(
            entry_name("BC-Safe", 1, TrainingData::Starter),
            entry_name("BC-Safe", 1, TrainingData::FullBuild)
        );
    }
}
