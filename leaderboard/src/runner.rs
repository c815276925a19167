//! Evaluators: tasks that drain the submission queue. Each claims a job with a lease, heartbeats while it plays the
//! job's episodes through the simulator pool (recording how many are done), and stores the result only while it
//! still holds the lease. An evaluator that dies with its server leaves a lease that runs out; any evaluator then
//! re-runs the job from the start, with the same held seeds, so the result is the same.
//!
//! Every evaluator runs under a supervisor (`spawn`): one that panics is logged, counted
//! (`dsrl_evaluator_restarts_total`), shown in `/healthz`, its job put back in the queue (or failed once it has had
//! `max_attempts` claims), and it is started again. A job that runs past its deadline (a multiple of its task's
//! recent scoring time, within `max_evaluation_seconds`) fails with the reason; a cancelled one is stopped within a
//! second, its policy processes with it.

use std::sync::Arc;
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::Duration;

use bytes::Bytes;
use dsrl_policy::Policy;
use dsrl_policy::checkpoint;

use dsrl_evaluation::inference::{IsolatedPolicy, PolicySource};

use super::Leaderboard;
use super::queue::{self, EpisodeRow, Failure, Job};
use dsrl_evaluation::evaluator::play_episodes_counted;
use dsrl_service::error::{ApiError, ErrorCode};

/// How a job ended.
enum Outcome {
    Scored(Vec<EpisodeRow>),
    /// The checkpoint cannot be evaluated (it would fail again).
    Failed(String),
    /// The job ran past its deadline. Not the checkpoint's fault as far as anyone can tell: each of its policy's
    /// answers came within the per-request limit (or it would have failed for that), so the time went to a
    /// machine busier than the task's recent scorings. The job fails, and the same checkpoint may be submitted
    /// again (the submitter's quotas bound how often).
    PastDeadline(String),
    /// Something outside the checkpoint failed (a simulator worker died, a policy process was killed from
    /// outside): the job goes back to the queue.
    Interrupted(String),
}

/// Starts `config.evaluators` supervised evaluators; they run until the runtime stops.
pub fn spawn(leaderboard: Arc<Leaderboard>) {
    for index in 0..leaderboard.config.evaluators as usize {
        leaderboard.evaluators.add(index);
        tokio::spawn(supervise(leaderboard.clone(), index));
    }
}

fn new_owner(index: usize) -> String {
    format!(
        "{}-{}-{index}",
        std::process::id(),
        dsrl_service::secrets::random_hex()
            .unwrap_or_default()
            .get(..8)
            .unwrap_or("0")
    )
}

/// Runs evaluator `index`, starting it again whenever it panics.
async fn supervise(leaderboard: Arc<Leaderboard>, index: usize) {
    loop {
        let owner = new_owner(index);
        leaderboard.evaluators.started(index, &owner);
        let run = tokio::spawn(evaluator(leaderboard.clone(), index, owner.clone()));
        let panic = match run.await {
            Ok(()) => return,
            Err(e) if e.is_panic() => super::supervision::panic_message(e.into_panic()),
            // Cancelled: the runtime is shutting down.
            Err(_) => return,
        };
        let job = leaderboard.evaluators.panicked(index, &panic);
        tracing::error!(evaluator = index, %owner, job, panic = %panic, "an evaluator panicked; starting it again");
        if let Some(id) = job {
            let reason = format!("the evaluator scoring it failed ({panic}); the job went back to the queue");
            let max = leaderboard.config.max_attempts;
            if let Err(e) = queue::release_or_fail(&leaderboard.db, id, &owner, &reason, max).await {
                tracing::error!(id, error = %e, "returning a panicked evaluator's job");
            }
        }
        leaderboard.wake.notify_waiters();
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
}

async fn evaluator(leaderboard: Arc<Leaderboard>, index: usize, owner: String) {
    let lease_ms = (leaderboard.config.lease_seconds.max(1) * 1000) as i64;
    let mut said_alive: Option<std::time::Instant> = None;
    loop {
        // Waits for a simulator worker before taking a job, so a server without workers only queues.
        if !leaderboard.simulators.workers().iter().any(|w| w.healthy) {
            tokio::time::sleep(Duration::from_millis(500)).await;
            continue;
        }
        // Queue estimates count the evaluators that say they are alive (and able to score: workers are up).
        if said_alive.is_none_or(|t| t.elapsed() >= Duration::from_millis(queue::LIVENESS_INTERVAL_MS as u64)) {
            match queue::evaluator_alive(&leaderboard.db, &owner).await {
                Ok(()) => said_alive = Some(std::time::Instant::now()),
                Err(e) => tracing::warn!(error = %e, "recording that the evaluator is alive"),
            }
        }
        let job = match queue::claim(&leaderboard.db, &owner, lease_ms, leaderboard.config.max_attempts).await {
            Ok(Some(job)) => job,
            Ok(None) => {
                // A new submission wakes us; a lapsed lease is noticed within a second.
                let _ = tokio::time::timeout(Duration::from_secs(1), leaderboard.wake.notified()).await;
                continue;
            }
            Err(e) => {
                tracing::error!(error = %e, "claiming an evaluation job");
                tokio::time::sleep(Duration::from_secs(1)).await;
                continue;
            }
        };
        leaderboard.evaluators.claimed(index, job.id);
        tracing::info!(id = job.id, task = %job.task, attempt = job.attempts, %owner, "evaluation started");
        let started = std::time::Instant::now();
        let deadline = leaderboard.deadline(&job.task).await;
        let progress = AtomicU32::new(0);
        let outcome = tokio::select! {
            outcome = tokio::time::timeout(deadline, evaluate(&leaderboard, &job, &progress)) => {
                Some(outcome.unwrap_or_else(|_| {
                    Outcome::PastDeadline(format!(
                        "the evaluation ran past its deadline of {} s ({} episodes of {} done; the deadline is \
                         leaderboard.deadline_factor times the task's recent scoring time, at most \
                         leaderboard.max_evaluation_seconds); the same checkpoint may be submitted again",
                        deadline.as_secs(),
                        progress.load(Ordering::Relaxed),
                        job.episodes_per_threshold as usize * leaderboard.task(&job.task).map_or(3, |t| t.cost_thresholds.len())
                    ))
                }))
            }
            () = keep_lease(&leaderboard, index, &job, &owner, lease_ms, &progress) => None,
        };
        let stored = match outcome {
            None => {
                tracing::warn!(id = job.id, "evaluation abandoned: the job was cancelled or taken over");
                Ok(())
            }
            Some(Outcome::Scored(episodes)) => store(&leaderboard, &job, &owner, &episodes).await.map(|kept| {
                tracing::info!(
                    id = job.id,
                    kept,
                    seconds = started.elapsed().as_secs_f64(),
                    "evaluation finished"
                );
            }),
            Some(Outcome::Failed(reason)) => {
                tracing::warn!(id = job.id, %reason, "evaluation failed");
                queue::fail(&leaderboard.db, job.id, &owner, &reason, Failure::Checkpoint).await
            }
            Some(Outcome::PastDeadline(reason)) => {
                tracing::warn!(id = job.id, %reason, "evaluation past its deadline");
                queue::fail(&leaderboard.db, job.id, &owner, &reason, Failure::Infrastructure).await
            }
            Some(Outcome::Interrupted(reason)) => {
                tracing::warn!(id = job.id, %reason, "evaluation interrupted; the job goes back to the queue");
                let max = leaderboard.config.max_attempts;
                let released = queue::release_or_fail(&leaderboard.db, job.id, &owner, &reason, max).await;
                tokio::time::sleep(Duration::from_secs(1)).await;
                released
            }
        };
        if let Err(e) = stored {
            tracing::error!(id = job.id, error = %e, "recording an evaluation result");
        }
        // Requests waiting for this submission to end look at it now.
        leaderboard.ended.notify_waiters();
        leaderboard.evaluators.idle(index);
    }
}

/// Checks every second that the job is still this evaluator's (a cancel stops it within that, and at once when it
/// was cancelled on this server), and heartbeats with the episodes done every third of the lease; returns when the
/// job is no longer this evaluator's.
async fn keep_lease(
    leaderboard: &Leaderboard,
    index: usize,
    job: &Job,
    owner: &str,
    lease_ms: i64,
    progress: &AtomicU32,
) {
    let beat = Duration::from_millis((lease_ms / 3).max(100) as u64);
    let mut last_beat = std::time::Instant::now();
    loop {
        let _ = tokio::time::timeout(Duration::from_secs(1), leaderboard.cancelled.notified()).await;
        let held = if last_beat.elapsed() >= beat {
            last_beat = std::time::Instant::now();
            let done = progress.load(Ordering::Relaxed);
            let beat = queue::heartbeat(&leaderboard.db, job.id, owner, lease_ms, done).await;
            if beat.is_ok() {
                leaderboard.evaluators.heartbeat(index);
            }
            beat
        } else {
            queue::still_held(&leaderboard.db, job.id, owner).await
        };
        match held {
            Ok(true) => {}
            Ok(false) => return,
            // A database hiccup: the lease has two more beats before it runs out.
            Err(e) => tracing::warn!(id = job.id, error = %e, "heartbeat failed"),
        }
    }
}

async fn store(leaderboard: &Leaderboard, job: &Job, owner: &str, episodes: &[EpisodeRow]) -> Result<bool, ApiError> {
    let task = leaderboard.task(&job.task)?;
    let score = dsrl_scoring::leaderboard::entry_score(task, episodes)
        .ok_or_else(|| ApiError::Internal(format!("job {} was scored without episodes", job.id)))?;
    let scored_by = crate::scorer_build(&leaderboard.simulators.workers());
    let scores = queue::Scores {
        episodes,
        normalized_reward: score.reward,
        normalized_cost: score.cost,
        protocol_version: &leaderboard.protocol.version,
    };
    queue::finish(&leaderboard.db, job.id, owner, &scores, &scored_by).await
}

/// A test-only fault, compiled into debug builds alone: a submission named `DSRL_TEST_PANIC_ON_NAME` makes its
/// evaluator panic, so the end-to-end tests can check the supervisor.
#[cfg(debug_assertions)]
async fn injected_fault(leaderboard: &Leaderboard, job: &Job) {
    if let Ok(name) = std::env::var("DSRL_TEST_PANIC_ON_NAME")
        && let Ok(row) = queue::get(&leaderboard.db, job.id).await
        && row.name == name
    {
        panic!("test fault: DSRL_TEST_PANIC_ON_NAME={name}");
    }
}

/// A checkpoint ready to play where scoring plays it: built here (tests that embed the server) or handed to a
/// memory-capped child process (`inference`).
pub(crate) enum PreparedPolicy {
    Local(Box<Policy>),
    Isolated(IsolatedPolicy),
}

impl PreparedPolicy {
    pub(crate) fn source(&self) -> PolicySource<'_> {
        match self {
            PreparedPolicy::Local(policy) => PolicySource::Local(policy),
            PreparedPolicy::Isolated(isolated) => PolicySource::Isolated(isolated),
        }
    }
}

/// Whether a checkpoint's forward pass is cheap enough to act inside the simulator workers: its declared cost per
/// environment at most `max_multiply_adds` (a config that does not parse acts nowhere: loading it fails the job).
fn acts_in_workers(config: &[u8], max_multiply_adds: u64) -> bool {
    max_multiply_adds > 0
        && checkpoint::parse_config(config).is_ok_and(|c| c.step_cost().multiply_adds <= max_multiply_adds)
}

/// A stored checkpoint's bytes made ready to play, as this process plays submitted policies (the evaluators and
/// the replays alike).
pub(crate) fn prepare_policy(
    leaderboard: &Leaderboard,
    config: Bytes,
    weights: Bytes,
) -> Result<PreparedPolicy, dsrl_policy::PolicyError> {
    match &leaderboard.policy_program {
        Some(program) => Ok(PreparedPolicy::Isolated(IsolatedPolicy {
            program: program.clone(),
            memory_limit_bytes: leaderboard.config.policy_memory_limit_bytes,
            request_timeout: Duration::from_secs(leaderboard.config.policy_request_seconds.max(1)),
            act_in_workers: acts_in_workers(&config, leaderboard.config.act_in_workers_max_multiply_adds),
            config,
            weights,
        })),
        None => {
            let config = checkpoint::parse_config(&config)?;
            let tensors = checkpoint::parse_weights(&weights)?;
            Ok(PreparedPolicy::Local(Box::new(Policy::load(&config, &tensors)?)))
        }
    }
}

/// Plays `episodes_per_threshold` held-seed episodes at each of the task's thresholds, all thresholds at once.
async fn evaluate(leaderboard: &Leaderboard, job: &Job, progress: &AtomicU32) -> Outcome {
    #[cfg(debug_assertions)]
    injected_fault(leaderboard, job).await;
    let task = match leaderboard.task(&job.task) {
        Ok(task) => task,
        Err(e) => return Outcome::Failed(e.to_string()),
    };
    let mut policies = Vec::new();
    for record in &job.checkpoints {
        let (config_bytes, weights_bytes) = match leaderboard.load(record).await {
            Ok(bytes) => bytes,
            Err(e) => return Outcome::Interrupted(format!("reading the checkpoint: {e}")),
        };
        match prepare_policy(leaderboard, config_bytes, weights_bytes) {
            Ok(policy) => policies.push((record.cost_threshold, policy)),
            Err(e) => return Outcome::Failed(format!("loading the checkpoint {}: {e}", record.slot)),
        }
    }
    let plays = task.cost_thresholds.iter().enumerate().map(|(index, &threshold)| {
        let policy = policies
            .iter()
            .find(|(t, _)| t.is_none() || *t == Some(threshold))
            .map(|(_, p)| p.source());
        let seeds = leaderboard
            .seeds
            .seeds(task.id.as_str(), index, job.episodes_per_threshold);
        async move {
            let policy =
                policy.ok_or_else(|| ApiError::Internal(format!("no checkpoint for threshold {threshold}")))?;
            let scores = play_episodes_counted(
                &leaderboard.simulators,
                task,
                policy,
                threshold,
                &seeds,
                leaderboard.config.envs_per_session as usize,
                1,
                progress,
            )
            .await?;
            Ok::<_, ApiError>(
                scores
                    .into_iter()
                    .enumerate()
                    .map(|(episode, s)| EpisodeRow {
                        cost_threshold: threshold,
                        episode: episode as u32,
                        reward_return: s.reward_return,
                        cost_return: s.cost_return,
                        length: s.length,
                    })
                    .collect::<Vec<_>>(),
            )
        }
    });
    match futures::future::try_join_all(plays).await {
        Ok(rows) => Outcome::Scored(rows.into_iter().flatten().collect()),
        Err(e) if matches!(e.code(), ErrorCode::Unavailable) => Outcome::Interrupted(e.to_string()),
        Err(e) => Outcome::Failed(e.to_string()),
    }
}
