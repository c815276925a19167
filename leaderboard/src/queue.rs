//! The submissions table as a durable job queue. States: queued → running → finished | failed | cancelled.
//! An evaluator claims the oldest queued job, or a running one whose lease ran out (its evaluator died), by
//! writing its own lease; it heartbeats while it plays and writes the result only while it still holds the lease,
//! so a job taken over by another evaluator is finished exactly once.

use prometheus_client::metrics::gauge::Gauge;
use sqlx::{AssertSqlSafe, Row};

use dsrl_service::db::Db;

use super::checkpoints::CheckpointRecord;
use dsrl_service::db::now_rfc3339;
use dsrl_service::error::ApiError;

pub use dsrl_service::db::now_ms;

/// A claimed job.
#[derive(Debug, Clone)]
pub struct Job {
    pub id: i64,
    pub task: String,
    pub checkpoints: Vec<CheckpointRecord>,
    pub episodes_per_threshold: u32,
    pub attempts: u32,
}

/// One evaluated episode (the suite's type: reference results hold the same rows).
pub use dsrl_suite::score::EpisodeResult as EpisodeRow;

/// A submission that holds its checkpoint against resubmission (the dedupe index's condition): not cancelled, and
/// not failed for a reason outside the checkpoint.
pub const HOLDS_CHECKPOINT: &str = "state != 'cancelled' AND NOT (state = 'failed' AND failure = 'infrastructure')";

/// Why a failed job failed: its checkpoint (it would fail again), or something outside it (the same checkpoint may
/// be submitted again).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Failure {
    Checkpoint,
    Infrastructure,
}

impl Failure {
    pub fn as_str(self) -> &'static str {
        match self {
            Failure::Checkpoint => "checkpoint",
            Failure::Infrastructure => "infrastructure",
        }
    }
}

pub struct NewSubmission<'a> {
    pub user_id: i64,
    pub task: &'a str,
    pub name: &'a str,
    pub checkpoint_sha256: &'a str,
    pub checkpoints: &'a [CheckpointRecord],
    pub episodes_per_threshold: u32,
    /// The dataset version the checkpoint says it was trained on.
    pub dataset_version: Option<&'a str>,
}

/// The `Retry-After` of a refusal for too many live submissions: a job's scoring takes about this long.
pub const CONCURRENT_QUOTA_RETRY_SECONDS: u64 = 60;

pub struct Quotas {
    pub per_day: u32,
    pub concurrent: u32,
}

/// Inserts a queued submission after the quota checks, in one transaction. The user's row is locked first, so
/// two replicas inserting for one user check the quotas one after the other. Deduplication is the unique index
/// `submissions_checkpoint`: a second live submission of a checkpoint fails the insert, whichever replica got it.
/// A duplicate is looked for first only so that it is reported as one even when the quota is also spent.
pub async fn insert(db: &Db, new: NewSubmission<'_>, quotas: &Quotas) -> Result<i64, ApiError> {
    if let Some(error) = already_submitted(db, &new).await? {
        return Err(error);
    }
    let mut tx = db.begin().await?;
    sqlx::query(AssertSqlSafe(format!(
        "SELECT id FROM users WHERE id = $1{}",
        db.backend().for_update()
    )))
    .bind(new.user_id)
    .fetch_optional(&mut *tx)
    .await?;
    let now = now_ms();
    // Cancelled submissions are not counted: withdrawn work used nothing of the day's evaluation.
    let day_ms = 24 * 3600 * 1000;
    let row = sqlx::query(
        "SELECT
            (SELECT COUNT(*) FROM submissions WHERE user_id = $1 AND created_ms > $2 AND state != 'cancelled'),
            (SELECT MIN(created_ms) FROM submissions WHERE user_id = $1 AND created_ms > $2 AND state != 'cancelled'),
            (SELECT COUNT(*) FROM submissions WHERE user_id = $1 AND state IN ('queued', 'running'))",
    )
    .bind(new.user_id)
    .bind(now - day_ms)
    .fetch_one(&mut *tx)
    .await?;
    let (today, oldest, live): (i64, Option<i64>, i64) = (row.try_get(0)?, row.try_get(1)?, row.try_get(2)?);
    if today >= i64::from(quotas.per_day) {
        // The day's oldest counted submission leaves the window first.
        let retry_after = oldest.map_or(60, |t| ((t + day_ms - now) / 1000).max(1) as u64);
        return Err(ApiError::RateLimited {
            message: format!(
                "quota exceeded: {today} submissions in the last 24 hours; the limit is {} a day",
                quotas.per_day
            ),
            retry_after,
        });
    }
    if live >= i64::from(quotas.concurrent) {
        return Err(ApiError::RateLimited {
            message: format!(
                "quota exceeded: {live} of your submissions are queued or running; the limit is {} at once",
                quotas.concurrent
            ),
            retry_after: CONCURRENT_QUOTA_RETRY_SECONDS,
        });
    }
    let inserted = sqlx::query(
        "INSERT INTO submissions (user_id, task, name, checkpoint_sha256, checkpoints, state, created_at, created_ms,
                                  episodes_per_threshold, dataset_version)
         VALUES ($1, $2, $3, $4, $5, 'queued', $6, $7, $8, $9)
         RETURNING id",
    )
    .bind(new.user_id)
    .bind(new.task)
    .bind(new.name)
    .bind(new.checkpoint_sha256)
    .bind(serde_json::to_string(new.checkpoints).map_err(ApiError::internal)?)
    .bind(now_rfc3339())
    .bind(now)
    .bind(i64::from(new.episodes_per_threshold))
    .bind(new.dataset_version)
    .fetch_one(&mut *tx)
    .await;
    let id: i64 = match inserted {
        Ok(row) => row.try_get(0)?,
        Err(sqlx::Error::Database(e)) if e.is_unique_violation() => {
            drop(tx);
            return Err(already_submitted(db, &new).await?.unwrap_or_else(|| {
                // The holder was cancelled between the refused insert and this look.
                ApiError::AlreadyExists(format!(
                    "this checkpoint (sha256 {}) was being submitted for {} at the same time; try again",
                    new.checkpoint_sha256, new.task
                ))
            }));
        }
        Err(e) => return Err(e.into()),
    };
    tx.commit().await?;
    Ok(id)
}

/// The error for a checkpoint that a live submission already holds, naming that submission.
async fn already_submitted(db: &Db, new: &NewSubmission<'_>) -> Result<Option<ApiError>, ApiError> {
    let existing = sqlx::query(AssertSqlSafe(format!(
        "SELECT id, state FROM submissions WHERE task = $1 AND checkpoint_sha256 = $2 AND {HOLDS_CHECKPOINT}"
    )))
    .bind(new.task)
    .bind(new.checkpoint_sha256)
    .fetch_optional(db.pool())
    .await?;
    let Some(row) = existing else { return Ok(None) };
    let (id, state): (i64, String) = (row.try_get(0)?, row.try_get(1)?);
    Ok(Some(ApiError::AlreadyExists(format!(
        "this checkpoint (sha256 {}) was already submitted for {} as submission {id} ({state})",
        new.checkpoint_sha256, new.task
    ))))
}

/// Fails running jobs whose lease ran out after `max_attempts` claims, then claims the next runnable job in the fair
/// order (`fair_queue`): each user's oldest waiting job comes before anyone's second, and among those the user served
/// longest ago (never served first) goes first. So one user's queue of slow submissions delays another user's by at
/// most the job being scored. On PostgreSQL the pick skips rows another evaluator is claiming (`FOR UPDATE SKIP
/// LOCKED`), so concurrent claims neither wait for each other nor take the same job.
pub async fn claim(db: &Db, owner: &str, lease_ms: i64, max_attempts: u32) -> Result<Option<Job>, ApiError> {
    let now = now_ms();
    sqlx::query(
        "UPDATE submissions SET state = 'failed', lease_owner = NULL, finished_at = $3, failure = 'infrastructure',
             reason = 'the evaluation was interrupted ' || attempts || ' times (evaluator or simulator lost)'
         WHERE state = 'running' AND lease_expires_ms < $1 AND attempts >= $2",
    )
    .bind(now)
    .bind(i64::from(max_attempts))
    .bind(now_rfc3339())
    .execute(db.pool())
    .await?;
    // A transaction whose commit is checked: in autocommit the RETURNING row arrives before the implicit commit, so
    // a commit that failed would hand out a job the database does not hold as claimed.
    let mut tx = db.begin().await?;
    let row = sqlx::query(AssertSqlSafe(format!(
        "UPDATE submissions
         SET state = 'running', attempts = attempts + 1, lease_owner = $1, lease_expires_ms = $2,
             started_at = COALESCE(started_at, $3), claimed_ms = $4, heartbeat_ms = $4, episodes_done = 0
         WHERE id = ({})
         RETURNING id, task, checkpoints, episodes_per_threshold, attempts",
        pick(db.backend(), "$4")
    )))
    .bind(owner)
    .bind(now + lease_ms)
    .bind(now_rfc3339())
    .bind(now)
    .fetch_optional(&mut *tx)
    .await?;
    tx.commit().await?;
    let Some(row) = row else { return Ok(None) };
    let checkpoints: String = row.try_get(2)?;
    Ok(Some(Job {
        id: row.try_get(0)?,
        task: row.try_get(1)?,
        checkpoints: serde_json::from_str(&checkpoints).map_err(ApiError::internal)?,
        episodes_per_threshold: row.try_get::<i64, _>(3)? as u32,
        attempts: row.try_get::<i64, _>(4)? as u32,
    }))
}

/// The condition of a job waiting for an evaluator, on the columns of the table aliased `table`: queued, or running
/// under a lease that ran out before the time (milliseconds) in the parameter `now`. One definition for the claim,
/// the queue positions and the queue depth.
fn waiting(table: &str, now: &str) -> String {
    format!("({table}.state = 'queued' OR ({table}.state = 'running' AND {table}.lease_expires_ms < {now}))")
}

/// The waiting jobs with what their fair order (`FAIR_ORDER`) sorts by: round-robin across users, where a user's
/// k-th waiting job is in round k (`round`, counted from 1); within a round, the user whose last claim is oldest goes
/// first (`last_claim`); then submission order. One user's many submissions cannot hold back another's first,
/// whether or not an evaluator has claimed anything yet.
///
/// The round is a window function, one pass over the waiting jobs. It was a count of the user's earlier waiting
/// jobs for each waiting job, which made a claim quadratic in the queue's length: 65 ms at 1,000 queued jobs of one
/// user, all of it under SQLite's write lock, so that concurrent claims and submissions waited and, with a longer
/// queue, ran past `busy_timeout` ("database is locked"). The last claim is one index lookup per job
/// (`submissions_user_claims`).
fn fair_queue(now: &str) -> String {
    format!(
        "SELECT w.id, w.task, ROW_NUMBER() OVER (PARTITION BY w.user_id ORDER BY w.id) AS round,
                (SELECT COALESCE(MAX(c.claimed_ms), 0) FROM submissions c WHERE c.user_id = w.user_id) AS last_claim
         FROM submissions w WHERE {}",
        waiting("w", now)
    )
}

/// The fair order of `fair_queue`'s jobs, aliased `q`.
const FAIR_ORDER: &str = "q.round, q.last_claim, q.id";

/// How many jobs at the head of the fair order a claim considers. Only jobs that other evaluators are claiming at
/// the same instant are passed over, so this bounds the evaluators that can claim at once without one of them
/// finding nothing (it then tries again a second later, as on an empty queue).
const CLAIM_CANDIDATES: usize = 128;

/// The subquery that picks the job to claim: the first of the head of the fair order (computed once, `MATERIALIZED`)
/// that is still waiting, and on PostgreSQL not being claimed by another evaluator (`FOR UPDATE OF s SKIP LOCKED`).
///
/// - The fair order is computed apart from the row it locks because PostgreSQL allows no locking clause beside a
///   window function. Joined directly, PostgreSQL's plan for a table it had not yet analyzed (a fresh server's
///   first burst of submissions) recomputed the window for every waiting job, quadratic again: 0.5 s a claim at a
///   few hundred jobs. The materialized head is at most `CLAIM_CANDIDATES` rows, whatever the plan.
/// - The waiting condition is stated again on the locked row `s`: a claim that meets a row another claim has just
///   committed re-checks that row's new version against the conditions on `s` alone (READ COMMITTED's recheck; `q`
///   keeps its snapshot), so without it two evaluators would take one job.
fn pick(backend: dsrl_service::db::Backend, now: &str) -> String {
    format!(
        "WITH q AS MATERIALIZED ({} ORDER BY round, last_claim, id LIMIT {CLAIM_CANDIDATES})
         SELECT s.id FROM q JOIN submissions s ON s.id = q.id
         WHERE {}
         ORDER BY {FAIR_ORDER}
         LIMIT 1{}",
        fair_queue(now),
        waiting("s", now),
        backend.skip_locked("s")
    )
}

/// Jobs waiting for an evaluator: queued, or running under a lease that ran out.
pub async fn depth(db: &Db) -> Result<i64, ApiError> {
    let row = sqlx::query(AssertSqlSafe(format!(
        "SELECT COUNT(*) FROM submissions s WHERE {}",
        waiting("s", "$1")
    )))
    .bind(now_ms())
    .fetch_one(db.pool())
    .await?;
    Ok(row.try_get(0)?)
}

/// Registers the queue depth as the gauge `<prefix>_evaluation_queue_depth` (API replicas and evaluators alike;
/// the autoscaler of simulator workers follows it). `refresh_depth_gauge` sets it at scrape time.
pub fn register_depth_gauge(registry: &mut prometheus_client::registry::Registry) -> Gauge {
    let gauge = Gauge::default();
    registry.register(
        "evaluation_queue_depth",
        "Leaderboard submissions waiting for an evaluator (queued, or running with a lapsed lease), read at scrape time",
        gauge.clone(),
    );
    gauge
}

/// Reads the queue's depth into its gauge; a database error leaves the last value and is logged.
pub async fn refresh_depth_gauge(gauge: &Gauge, db: &Db) {
    match depth(db).await {
        Ok(depth) => {
            gauge.set(depth);
        }
        Err(e) => tracing::warn!(error = %e, "reading the evaluation queue depth"),
    }
}

/// Extends the lease and records the episodes scored so far; `false` when the job is no longer this evaluator's
/// (taken over, or cancelled).
pub async fn heartbeat(db: &Db, id: i64, owner: &str, lease_ms: i64, episodes_done: u32) -> Result<bool, ApiError> {
    let now = now_ms();
    let done = sqlx::query(
        "UPDATE submissions SET lease_expires_ms = $3, heartbeat_ms = $4, episodes_done = $5
         WHERE id = $1 AND lease_owner = $2 AND state = 'running'",
    )
    .bind(id)
    .bind(owner)
    .bind(now + lease_ms)
    .bind(now)
    .bind(i64::from(episodes_done))
    .execute(db.pool())
    .await?;
    Ok(done.rows_affected() == 1)
}

/// Whether the job is still this evaluator's to play (a read, cheap enough to ask every second: a cancel stops the
/// job's children within that).
pub async fn still_held(db: &Db, id: i64, owner: &str) -> Result<bool, ApiError> {
    let row = sqlx::query("SELECT 1 FROM submissions WHERE id = $1 AND lease_owner = $2 AND state = 'running'")
        .bind(id)
        .bind(owner)
        .fetch_optional(db.pool())
        .await?;
    Ok(row.is_some())
}

/// A job's result: every episode, the scores, and the protocol version they were scored under.
pub struct Scores<'a> {
    pub episodes: &'a [EpisodeRow],
    pub normalized_reward: f64,
    pub normalized_cost: f64,
    pub protocol_version: &'a str,
}

/// Stores every episode and the scores, with the build that scored them (`crate::scorer_build`), if this evaluator
/// still holds the job; returns whether it did.
pub async fn finish(db: &Db, id: i64, owner: &str, result: &Scores<'_>, scored_by: &str) -> Result<bool, ApiError> {
    let mut tx = db.begin().await?;
    let done = sqlx::query(
        "UPDATE submissions SET state = 'finished', lease_owner = NULL, finished_at = $3, reason = NULL, failure = NULL,
             normalized_reward = $4, normalized_cost = $5, protocol_version = $6, scoring_ms = $7 - claimed_ms,
             episodes_done = $8, scored_by = $9
         WHERE id = $1 AND lease_owner = $2 AND state = 'running'",
    )
    .bind(id)
    .bind(owner)
    .bind(now_rfc3339())
    .bind(result.normalized_reward)
    .bind(result.normalized_cost)
    .bind(result.protocol_version)
    .bind(now_ms())
    .bind(result.episodes.len() as i64)
    .bind(scored_by)
    .execute(&mut *tx)
    .await?;
    if done.rows_affected() != 1 {
        return Ok(false);
    }
    insert_episodes(&mut tx, id, result.episodes).await?;
    tx.commit().await?;
    Ok(true)
}

async fn insert_episodes(
    tx: &mut sqlx::Transaction<'_, sqlx::Any>,
    id: i64,
    episodes: &[EpisodeRow],
) -> Result<(), ApiError> {
    for e in episodes {
        sqlx::query(
            "INSERT INTO evaluation_episodes
                (submission_id, cost_threshold, episode, reward_return, cost_return, length)
             VALUES ($1, $2, $3, $4, $5, $6)",
        )
        .bind(id)
        .bind(e.cost_threshold)
        .bind(i64::from(e.episode))
        .bind(e.reward_return)
        .bind(e.cost_return)
        .bind(i64::from(e.length))
        .execute(&mut **tx)
        .await?;
    }
    Ok(())
}

/// A finished result recorded elsewhere (a reference entry of `data/reference/results.jsonl`), stored as a
/// finished submission of `user_id` with its episodes.
pub struct Imported<'a> {
    pub user_id: i64,
    pub task: &'a str,
    pub name: &'a str,
    pub checkpoint_sha256: &'a str,
    pub started_at: &'a str,
    pub finished_at: &'a str,
    pub episodes_per_threshold: u32,
    pub dataset_version: &'a str,
    /// The reference record (JSON).
    pub reference: &'a str,
    /// The build that scored it, where the results file records it.
    pub scored_by: Option<&'a str>,
    pub result: Scores<'a>,
}

/// Stores an imported result in one transaction; `false` when a live submission already holds its checkpoint for
/// the task (nothing is stored then).
pub async fn insert_finished(db: &Db, new: &Imported<'_>) -> Result<bool, ApiError> {
    let mut tx = db.begin().await?;
    let inserted = sqlx::query(
        "INSERT INTO submissions (user_id, task, name, checkpoint_sha256, checkpoints, state, created_at, created_ms,
                                  started_at, finished_at, episodes_per_threshold, normalized_reward, normalized_cost,
                                  protocol_version, dataset_version, reference, scored_by)
         VALUES ($1, $2, $3, $4, '[]', 'finished', $5, $6, $5, $7, $8, $9, $10, $11, $12, $13, $14)
         RETURNING id",
    )
    .bind(new.user_id)
    .bind(new.task)
    .bind(new.name)
    .bind(new.checkpoint_sha256)
    .bind(new.started_at)
    .bind(now_ms())
    .bind(new.finished_at)
    .bind(i64::from(new.episodes_per_threshold))
    .bind(new.result.normalized_reward)
    .bind(new.result.normalized_cost)
    .bind(new.result.protocol_version)
    .bind(new.dataset_version)
    .bind(new.reference)
    .bind(new.scored_by)
    .fetch_one(&mut *tx)
    .await;
    let id: i64 = match inserted {
        Ok(row) => row.try_get(0)?,
        Err(sqlx::Error::Database(e)) if e.is_unique_violation() => return Ok(false),
        Err(e) => return Err(e.into()),
    };
    insert_episodes(&mut tx, id, new.result.episodes).await?;
    tx.commit().await?;
    Ok(true)
}

/// Replaces the record of an imported reference entry (its `reference` JSON: method, seed, training, code commit,
/// scoring), its scores unchanged: the same checkpoint and scoring, recorded anew (trained again by another commit).
pub async fn set_reference(db: &Db, id: i64, reference: &str) -> Result<(), ApiError> {
    sqlx::query("UPDATE submissions SET reference = $2 WHERE id = $1 AND reference IS NOT NULL")
        .bind(id)
        .bind(reference)
        .execute(db.pool())
        .await?;
    Ok(())
}

/// Withdraws one finished submission (cancelled with the reason: kept in the database, off the tables).
pub async fn withdraw(db: &Db, id: i64, reason: &str) -> Result<(), ApiError> {
    sqlx::query("UPDATE submissions SET state = 'cancelled', reason = $2 WHERE id = $1 AND state = 'finished'")
        .bind(id)
        .bind(reason)
        .execute(db.pool())
        .await?;
    Ok(())
}

/// Withdraws `user_id`'s finished submissions whose (task, checkpoint) is not in `keep` (cancelled, with the
/// reason: kept in the database, off the tables); returns how many.
pub async fn withdraw_except(db: &Db, user_id: i64, keep: &[(String, String)], reason: &str) -> Result<u64, ApiError> {
    let rows =
        sqlx::query("SELECT id, task, checkpoint_sha256 FROM submissions WHERE user_id = $1 AND state = 'finished'")
            .bind(user_id)
            .fetch_all(db.pool())
            .await?;
    let mut withdrawn = 0;
    for row in rows {
        let (id, task, sha): (i64, String, String) = (row.try_get(0)?, row.try_get(1)?, row.try_get(2)?);
        if keep.iter().any(|(t, s)| *t == task && *s == sha) {
            continue;
        }
        withdraw(db, id, reason).await?;
        withdrawn += 1;
    }
    Ok(withdrawn)
}

/// Ends a job with the reason and the kind of failure, if this evaluator still holds it.
pub async fn fail(db: &Db, id: i64, owner: &str, reason: &str, failure: Failure) -> Result<(), ApiError> {
    sqlx::query(
        "UPDATE submissions SET state = 'failed', lease_owner = NULL, finished_at = $3, reason = $4, failure = $5
         WHERE id = $1 AND lease_owner = $2 AND state = 'running'",
    )
    .bind(id)
    .bind(owner)
    .bind(now_rfc3339())
    .bind(reason)
    .bind(failure.as_str())
    .execute(db.pool())
    .await?;
    Ok(())
}

/// Gives a job back to the queue after something outside its checkpoint failed, or fails it (an infrastructure
/// failure, so it may be submitted again) once it has been claimed `max_attempts` times.
pub async fn release_or_fail(db: &Db, id: i64, owner: &str, reason: &str, max_attempts: u32) -> Result<(), ApiError> {
    sqlx::query(
        "UPDATE submissions
         SET state = CASE WHEN attempts >= $4 THEN 'failed' ELSE 'queued' END,
             failure = CASE WHEN attempts >= $4 THEN 'infrastructure' ELSE NULL END,
             finished_at = CASE WHEN attempts >= $4 THEN $5 ELSE NULL END,
             lease_owner = NULL,
             reason = CASE WHEN attempts >= $4 THEN $3 || ' (the last of ' || attempts || ' attempts)' ELSE $3 END
         WHERE id = $1 AND lease_owner = $2 AND state = 'running'",
    )
    .bind(id)
    .bind(owner)
    .bind(reason)
    .bind(i64::from(max_attempts))
    .bind(now_rfc3339())
    .execute(db.pool())
    .await?;
    Ok(())
}

/// Gives a job back to the queue (a transient failure, such as a simulator worker lost mid-episode).
pub async fn release(db: &Db, id: i64, owner: &str, reason: &str) -> Result<(), ApiError> {
    sqlx::query(
        "UPDATE submissions SET state = 'queued', lease_owner = NULL, reason = $3
         WHERE id = $1 AND lease_owner = $2 AND state = 'running'",
    )
    .bind(id)
    .bind(owner)
    .bind(reason)
    .execute(db.pool())
    .await?;
    Ok(())
}

/// Who cancels a submission: its submitter, or the admin (any submission).
#[derive(Debug, Clone, Copy)]
pub enum Canceller {
    User(i64),
    Admin,
}

/// Cancels a queued or running submission, by its submitter or by the admin.
pub async fn cancel(db: &Db, id: i64, by: Canceller) -> Result<(), ApiError> {
    let row = sqlx::query("SELECT user_id, state FROM submissions WHERE id = $1")
        .bind(id)
        .fetch_optional(db.pool())
        .await?
        .ok_or_else(|| ApiError::NotFound(format!("no submission {id}")))?;
    let (owner, state): (i64, String) = (row.try_get(0)?, row.try_get(1)?);
    let reason = match by {
        Canceller::User(user_id) if user_id != owner => {
            return Err(ApiError::Forbidden(format!(
                "submission {id} belongs to another user; only its submitter (or the admin) can cancel it"
            )));
        }
        Canceller::User(_) => "cancelled by its submitter",
        Canceller::Admin => "cancelled by the admin",
    };
    let done = sqlx::query(
        "UPDATE submissions SET state = 'cancelled', lease_owner = NULL, finished_at = $2, reason = $3
         WHERE id = $1 AND state IN ('queued', 'running')",
    )
    .bind(id)
    .bind(now_rfc3339())
    .bind(reason)
    .execute(db.pool())
    .await?;
    if done.rows_affected() == 0 {
        return Err(ApiError::InvalidArgument(format!(
            "submission {id} is {state}; only queued or running submissions can be cancelled"
        )));
    }
    Ok(())
}

/// A submission row as stored.
#[derive(Debug, Clone)]
pub struct SubmissionRow {
    pub id: i64,
    pub user: String,
    pub task: String,
    pub name: String,
    pub checkpoint_sha256: String,
    pub checkpoints: Vec<CheckpointRecord>,
    pub state: String,
    pub reason: Option<String>,
    pub attempts: u32,
    pub created_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
    pub episodes_per_threshold: u32,
    pub normalized_reward: Option<f64>,
    pub normalized_cost: Option<f64>,
    pub protocol_version: Option<String>,
    pub dataset_version: Option<String>,
    /// A reference entry's record (JSON).
    pub reference: Option<String>,
    pub lease_owner: Option<String>,
    pub claimed_ms: Option<i64>,
    pub heartbeat_ms: Option<i64>,
    pub episodes_done: u32,
    pub failure: Option<String>,
    pub user_id: i64,
    /// The build that scored it (`crate::scorer_build` of the evaluator), where recorded.
    pub scored_by: Option<String>,
}

const SELECT_SUBMISSIONS: &str = "SELECT s.id, u.name AS submitter, s.task, s.name, s.checkpoint_sha256, s.checkpoints,
        s.state, s.reason, s.attempts, s.created_at, s.started_at, s.finished_at, s.episodes_per_threshold,
        s.normalized_reward, s.normalized_cost, s.protocol_version, s.dataset_version, s.reference, s.lease_owner,
        s.claimed_ms, s.heartbeat_ms, s.episodes_done, s.failure, s.user_id, s.scored_by
    FROM submissions s JOIN users u ON u.id = s.user_id";

fn submission_row(row: &sqlx::any::AnyRow) -> Result<SubmissionRow, ApiError> {
    let checkpoints: String = row.try_get("checkpoints")?;
    Ok(SubmissionRow {
        id: row.try_get("id")?,
        user: row.try_get("submitter")?,
        task: row.try_get("task")?,
        name: row.try_get("name")?,
        checkpoint_sha256: row.try_get("checkpoint_sha256")?,
        checkpoints: serde_json::from_str(&checkpoints).map_err(ApiError::internal)?,
        state: row.try_get("state")?,
        reason: row.try_get("reason")?,
        attempts: row.try_get::<i64, _>("attempts")? as u32,
        created_at: row.try_get("created_at")?,
        started_at: row.try_get("started_at")?,
        finished_at: row.try_get("finished_at")?,
        episodes_per_threshold: row.try_get::<i64, _>("episodes_per_threshold")? as u32,
        normalized_reward: row.try_get("normalized_reward")?,
        normalized_cost: row.try_get("normalized_cost")?,
        protocol_version: row.try_get("protocol_version")?,
        dataset_version: row.try_get("dataset_version")?,
        reference: row.try_get("reference")?,
        lease_owner: row.try_get("lease_owner")?,
        claimed_ms: row.try_get("claimed_ms")?,
        heartbeat_ms: row.try_get("heartbeat_ms")?,
        episodes_done: row.try_get::<i64, _>("episodes_done")? as u32,
        failure: row.try_get("failure")?,
        user_id: row.try_get("user_id")?,
        scored_by: row.try_get("scored_by")?,
    })
}

pub async fn get(db: &Db, id: i64) -> Result<SubmissionRow, ApiError> {
    // Only constant text is interpolated; values are bound.
    let row = sqlx::query(AssertSqlSafe(format!("{SELECT_SUBMISSIONS} WHERE s.id = $1")))
        .bind(id)
        .fetch_optional(db.pool())
        .await?
        .ok_or_else(|| ApiError::NotFound(format!("no submission {id}")))?;
    submission_row(&row)
}

/// A submission's state alone (`queued`, `running`, `finished`, `failed`, `cancelled`): the one-column read a
/// waiting request repeats, far cheaper than the full view.
pub async fn state(db: &Db, id: i64) -> Result<String, ApiError> {
    sqlx::query_scalar("SELECT state FROM submissions WHERE id = $1")
        .bind(id)
        .fetch_optional(db.pool())
        .await?
        .ok_or_else(|| ApiError::NotFound(format!("no submission {id}")))
}

/// The finished submissions that stand on the leaderboard: per (user, name, task) the latest one.
pub async fn standing(db: &Db) -> Result<Vec<SubmissionRow>, ApiError> {
    let rows = sqlx::query(AssertSqlSafe(format!(
        "{SELECT_SUBMISSIONS} WHERE s.state = 'finished' AND s.id = (
            SELECT MAX(t.id) FROM submissions t
            WHERE t.user_id = s.user_id AND t.name = s.name AND t.task = s.task AND t.state = 'finished')
         ORDER BY s.id"
    )))
    .fetch_all(db.pool())
    .await?;
    rows.iter().map(submission_row).collect()
}

pub async fn episodes(db: &Db, id: i64) -> Result<Vec<EpisodeRow>, ApiError> {
    let rows = sqlx::query(
        "SELECT cost_threshold, episode, reward_return, cost_return, length FROM evaluation_episodes
         WHERE submission_id = $1 ORDER BY cost_threshold, episode",
    )
    .bind(id)
    .fetch_all(db.pool())
    .await?;
    rows.iter()
        .map(|r| {
            Ok(EpisodeRow {
                cost_threshold: r.try_get(0)?,
                episode: r.try_get::<i64, _>(1)? as u32,
                reward_return: r.try_get(2)?,
                cost_return: r.try_get(3)?,
                length: r.try_get::<i64, _>(4)? as u32,
            })
        })
        .collect()
}

/// The jobs waiting for an evaluator in the order evaluators will claim them (the claim's fair order), with their
/// tasks.
pub async fn waiting_in_order(db: &Db) -> Result<Vec<(i64, String)>, ApiError> {
    let rows = sqlx::query(AssertSqlSafe(format!(
        "SELECT q.id, q.task FROM ({}) q ORDER BY {FAIR_ORDER}",
        fair_queue("$1")
    )))
    .bind(now_ms())
    .fetch_all(db.pool())
    .await?;
    rows.iter().map(|r| Ok((r.try_get(0)?, r.try_get(1)?))).collect()
}

/// Entry name and user name of every queued or running submission, by id, in one query.
pub async fn live_names(db: &Db) -> Result<std::collections::HashMap<i64, (String, String)>, ApiError> {
    let rows = sqlx::query(
        "SELECT s.id, s.name, u.name FROM submissions s JOIN users u ON u.id = s.user_id
         WHERE s.state IN ('queued', 'running')",
    )
    .fetch_all(db.pool())
    .await?;
    rows.iter()
        .map(|r| Ok((r.try_get(0)?, (r.try_get(1)?, r.try_get(2)?))))
        .collect()
}

/// The running jobs (with a live lease): id, task, claimed at (ms), episodes done, episodes in all.
pub async fn running(db: &Db) -> Result<Vec<RunningJob>, ApiError> {
    let rows = sqlx::query(
        "SELECT id, task, COALESCE(claimed_ms, 0), episodes_done, episodes_per_threshold, heartbeat_ms FROM submissions
         WHERE state = 'running' AND lease_expires_ms >= $1 ORDER BY id",
    )
    .bind(now_ms())
    .fetch_all(db.pool())
    .await?;
    rows.iter()
        .map(|r| {
            Ok((
                r.try_get(0)?,
                r.try_get(1)?,
                r.try_get(2)?,
                r.try_get::<i64, _>(3)? as u32,
                r.try_get::<i64, _>(4)? as u32,
                r.try_get(5)?,
            ))
        })
        .collect()
}

/// A running job under a live lease: id, task, when it was claimed (ms), episodes done, episodes per threshold,
/// the last heartbeat (ms).
pub type RunningJob = (i64, String, i64, u32, u32, Option<i64>);

/// How often an evaluator says it is alive while it waits for work.
pub const LIVENESS_INTERVAL_MS: i64 = 5_000;

/// Records that the evaluator `owner` is alive now (`evaluator_liveness`).
pub async fn evaluator_alive(db: &Db, owner: &str) -> Result<(), ApiError> {
    sqlx::query(
        "INSERT INTO evaluator_liveness (owner, seen_ms) VALUES ($1, $2)
         ON CONFLICT (owner) DO UPDATE SET seen_ms = excluded.seen_ms",
    )
    .bind(owner)
    .bind(now_ms())
    .execute(db.pool())
    .await?;
    Ok(())
}

/// Evaluators alive now, in any process: seen within three liveness intervals while waiting, or holding a running
/// job whose lease has not lapsed (a scoring evaluator heartbeats the job instead).
pub async fn live_evaluators(db: &Db) -> Result<i64, ApiError> {
    let now = now_ms();
    let row = sqlx::query(
        "SELECT COUNT(*) FROM (
             SELECT owner FROM evaluator_liveness WHERE seen_ms >= $1
             UNION
             SELECT lease_owner FROM submissions WHERE state = 'running' AND lease_expires_ms >= $2
                 AND lease_owner IS NOT NULL
         ) AS alive",
    )
    .bind(now - 3 * LIVENESS_INTERVAL_MS)
    .bind(now)
    .fetch_one(db.pool())
    .await?;
    Ok(row.try_get(0)?)
}

/// Mean scoring time in seconds of the last `last` finished jobs of each task that has any.
pub async fn recent_scoring_seconds(db: &Db, last: i64) -> Result<std::collections::HashMap<String, f64>, ApiError> {
    let rows = sqlx::query(
        "SELECT task, scoring_ms FROM submissions s
         WHERE state = 'finished' AND scoring_ms IS NOT NULL AND s.id IN (
             SELECT t.id FROM submissions t WHERE t.task = s.task AND t.state = 'finished' AND t.scoring_ms IS NOT NULL
             ORDER BY t.id DESC LIMIT $1)",
    )
    .bind(last)
    .fetch_all(db.pool())
    .await?;
    let mut sums: std::collections::HashMap<String, (f64, f64)> = std::collections::HashMap::new();
    for r in rows {
        let (task, ms): (String, i64) = (r.try_get(0)?, r.try_get(1)?);
        let entry = sums.entry(task).or_default();
        entry.0 += ms as f64 / 1000.0;
        entry.1 += 1.0;
    }
    Ok(sums.into_iter().map(|(t, (sum, n))| (t, sum / n)).collect())
}

/// How many submissions each (user id, task) has made, whatever became of them.
pub async fn submission_counts(db: &Db) -> Result<std::collections::HashMap<(i64, String), u32>, ApiError> {
    let rows = sqlx::query("SELECT user_id, task, COUNT(*) FROM submissions GROUP BY user_id, task")
        .fetch_all(db.pool())
        .await?;
    rows.iter()
        .map(|r| Ok(((r.try_get(0)?, r.try_get(1)?), r.try_get::<i64, _>(2)? as u32)))
        .collect()
}

/// Every submission of the user named `user`, newest first.
pub async fn by_user(db: &Db, user: &str) -> Result<Vec<SubmissionRow>, ApiError> {
    let rows = sqlx::query(AssertSqlSafe(format!(
        "{SELECT_SUBMISSIONS} WHERE u.name = $1 ORDER BY s.id DESC"
    )))
    .bind(user)
    .fetch_all(db.pool())
    .await?;
    rows.iter().map(submission_row).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One submission as the fair order sees it.
    struct QueueRow {
        id: i64,
        user: i64,
        waiting: bool,
        claimed_ms: Option<i64>,
    }

    /// The fair order computed from its definition, apart from the SQL: rounds by counting, last claims by scanning.
    fn fair_order_of(rows: &[QueueRow]) -> Vec<i64> {
        let mut keyed: Vec<(usize, i64, i64)> = rows
            .iter()
            .filter(|r| r.waiting)
            .map(|r| {
                let round = rows
                    .iter()
                    .filter(|w| w.waiting && w.user == r.user && w.id < r.id)
                    .count();
                let last = rows
                    .iter()
                    .filter(|c| c.user == r.user)
                    .filter_map(|c| c.claimed_ms)
                    .max()
                    .unwrap_or(0);
                (round, last, r.id)
            })
            .collect();
        keyed.sort();
        keyed.into_iter().map(|(_, _, id)| id).collect()
    }

    #[tokio::test]
    async fn claims_and_queue_positions_follow_the_fair_order() {
        let dir = tempfile::tempdir().unwrap();
        let db = Db::open(&dir.path().join("queue.sqlite")).await.unwrap();
        for user in 1..=4i64 {
            sqlx::query("INSERT INTO users (id, name, token_sha256, created_at) VALUES ($1, $2, $3, 'now')")
                .bind(user)
                .bind(format!("user-{user}"))
                .bind(format!("token-{user}"))
                .execute(db.pool())
                .await
                .unwrap();
        }
        // A queue with history: finished jobs with earlier claims, jobs running under a live lease (not waiting),
        // jobs whose lease lapsed (waiting again), and queued ones, spread unevenly over four users.
        let mut random = dsrl_suite::synthetic::SplitMix64::new(7);
        let mut next = |n: u64| random.next_u64() % n;
        let mut rows = Vec::new();
        for id in 1..=80i64 {
            let user = [1, 1, 1, 2, 2, 3, 4][next(7) as usize];
            let (kind, claimed_ms, lease) = match next(8) {
                0 | 1 => ("finished", Some(next(1000) as i64), None),
                2 => ("running", Some(next(1000) as i64), Some(i64::MAX / 2)),
                3 => ("running", Some(next(1000) as i64), Some(0)),
                _ => ("queued", None, None),
            };
            sqlx::query(
                "INSERT INTO submissions (id, user_id, task, name, checkpoint_sha256, checkpoints, state, attempts,
                     lease_expires_ms, created_at, created_ms, episodes_per_threshold, claimed_ms)
                 VALUES ($1, $2, 'OfflineBallRun-v0', 'job', $3, '[]', $4, 1, $5, 'now', $1, 20, $6)",
            )
            .bind(id)
            .bind(user)
            .bind(format!("digest-{id}"))
            .bind(kind)
            .bind(lease)
            .bind(claimed_ms)
            .execute(db.pool())
            .await
            .unwrap();
            let waiting = kind == "queued" || lease == Some(0);
            rows.push(QueueRow {
                id,
                user,
                waiting,
                claimed_ms,
            });
        }
        let mut claims = 0;
        loop {
            let expected = fair_order_of(&rows);
            let listed: Vec<i64> = waiting_in_order(&db)
                .await
                .unwrap()
                .into_iter()
                .map(|(id, _)| id)
                .collect();
            assert_eq!(listed, expected, "after {claims} claims");
            let Some(job) = claim(&db, "evaluator", 60_000, 3).await.unwrap() else {
                assert!(expected.is_empty(), "nothing claimed with {} waiting", expected.len());
                break;
            };
            assert_eq!(job.id, expected[0], "claim {claims}");
            let claimed_ms: i64 = sqlx::query("SELECT claimed_ms FROM submissions WHERE id = $1")
                .bind(job.id)
                .fetch_one(db.pool())
                .await
                .unwrap()
                .try_get(0)
                .unwrap();
            let row = rows.iter_mut().find(|r| r.id == job.id).unwrap();
            (row.waiting, row.claimed_ms) = (false, Some(claimed_ms));
            claims += 1;
        }
        assert!(claims > 40, "the queue held {claims} waiting jobs");
    }
}
