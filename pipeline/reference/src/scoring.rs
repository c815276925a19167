//! Handing entries in: each is submitted to the scoring server as soon as its models have trained (the server scores
//! it while the rest train), its final answer kept, and the scored entry written into the results file by
//! `dsrl-train reference-entry` (task, method, seed, budget, dataset version, commits, checkpoint digest, protocol,
//! every episode). Decisions go by the service's typed answers: its error codes and a submission's `failure`.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use dsrl_client::api::Client;
use dsrl_client::error::ClientError;

use crate::state::{EntryKey, StateDir, newer};

/// A scoring that failed for the service's sake (a simulator worker that stopped answering on an overloaded
/// machine fails a job after its attempts) is submitted again this many times at most.
const RETRIES: u32 = 2;
/// How often a submission being scored is looked at while the run waits for it.
const WAIT_POLL: Duration = Duration::from_secs(5);
/// How long the server may keep answering "unavailable" (or not answer) before the run gives up: a machine whose
/// cores are taken by other work can starve the server's database pool for minutes, which is no reason to stop a
/// run of hours.
const PATIENCE: Duration = Duration::from_secs(15 * 60);

/// Whether an answer says "not now" rather than "no": the server overloaded, or not answering in time.
fn transient(e: &ClientError) -> bool {
    match e {
        ClientError::Server { code, .. } => code == "unavailable",
        ClientError::Unreachable { .. } | ClientError::Timeout { .. } => true,
        _ => false,
    }
}

pub struct Scorer {
    pub client: Client,
    /// The user the submissions are made as (to find a submission made before a run was stopped).
    pub user: String,
    pub train: PathBuf,
    pub results: PathBuf,
    pub state: StateDir,
    /// Entries submitted and not yet recorded, oldest first.
    in_flight: Vec<EntryKey>,
    pub recorded: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wait {
    /// Look once: an entry still queued or running stays in flight.
    Look,
    /// Wait until it has ended.
    UntilEnded,
}

impl Scorer {
    pub fn new(client: Client, user: String, train: PathBuf, results: PathBuf, state: StateDir) -> Scorer {
        Scorer {
            client,
            user,
            train,
            results,
            state,
            in_flight: Vec::new(),
            recorded: 0,
        }
    }

    pub fn in_flight(&self) -> usize {
        self.in_flight.len()
    }

    /// Submits an entry whose models have all trained (or takes up the submission an earlier run made for it).
    pub async fn submit(&mut self, entry: &EntryKey) -> anyhow::Result<()> {
        let model = self.state.model_dir(entry);
        let id_file = self.state.submission_file(entry, "id");
        std::fs::create_dir_all(id_file.parent().expect("a parent"))?;
        let name = format!("{}-seed{}", entry.method.name(), entry.seed);
        // A submission made for another training of this model is stale.
        if id_file.exists() && newer(&model, &id_file) {
            self.state.forget_submission(entry)?;
        }
        // So is one kept from a scoring server whose state was reset since: its id names someone else's.
        if let Some(id) = read_id(&id_file) {
            let same = match self.submission(id).await {
                Ok(s) => s["task"] == entry.task.as_str() && s["name"] == name.as_str(),
                Err(ClientError::Server { status: 404, .. }) => false,
                Err(e) => return Err(e.into()),
            };
            if !same {
                self.state.forget_submission(entry)?;
            }
        }
        if read_id(&id_file).is_none() {
            let started = std::time::Instant::now();
            let id = loop {
                match self.client.submit(&model, &entry.task, &name).await {
                    Ok(answer) => break answer["id"].as_i64().context("the submission's answer has no id")?,
                    // Submitted before the run was stopped: the same checkpoint is held by that submission.
                    Err(ClientError::Server { code, .. }) if code == "already_exists" => {
                        break self.made_before(entry, &name).await?;
                    }
                    // The server's quota of submissions in flight: wait for those made.
                    Err(ClientError::Server { code, .. })
                        if code == "resource_exhausted" && !self.in_flight.is_empty() =>
                    {
                        self.record_finished(Wait::UntilEnded).await?;
                    }
                    Err(e) if transient(&e) && started.elapsed() < PATIENCE => {
                        eprintln!("{entry}: the server cannot take the submission now ({e}); trying again");
                        tokio::time::sleep(WAIT_POLL).await;
                    }
                    Err(e) => return Err(anyhow::Error::new(e).context(format!("submitting {entry}"))),
                }
            };
            dsrl_pipeline::write_atomically(&id_file, id.to_string().as_bytes())?;
            eprintln!("{entry} submitted as {id}");
        }
        self.in_flight.push(entry.clone());
        Ok(())
    }

    /// The id of the live submission this user made earlier under the entry's name.
    async fn made_before(&self, entry: &EntryKey, name: &str) -> anyhow::Result<i64> {
        let mine = self.client.user_submissions(&self.user).await?;
        mine.as_array()
            .into_iter()
            .flatten()
            .filter(|s| s["task"] == entry.task.as_str() && s["name"] == name)
            .filter(|s| !matches!(s["state"].as_str(), Some("failed" | "cancelled")))
            .filter_map(|s| s["id"].as_i64())
            .max()
            .with_context(|| {
                format!(
                    "the server says {entry}'s checkpoint was submitted already, but user {} has no such submission",
                    self.user
                )
            })
    }

    /// Records every in-flight entry whose scoring has ended; one that failed for the service's sake is submitted
    /// again. With `Wait::UntilEnded`, waits for each.
    pub async fn record_finished(&mut self, wait: Wait) -> anyhow::Result<()> {
        let entries = std::mem::take(&mut self.in_flight);
        let mut left = Vec::new();
        for entry in entries {
            if !self.finish(&entry, wait).await? {
                left.push(entry);
            } else if self.failed_scoring(&entry)? {
                Box::pin(self.submit(&entry)).await?;
            } else {
                self.record(&entry)?;
            }
        }
        // `submit` may have pushed entries meanwhile: they go after those still waiting.
        left.append(&mut self.in_flight);
        self.in_flight = left;
        Ok(())
    }

    /// Keeps the final answer of an entry's submission; false while it is queued or running (with `Wait::Look`).
    async fn finish(&self, entry: &EntryKey, wait: Wait) -> anyhow::Result<bool> {
        let json = self.state.submission_file(entry, "json");
        if json.exists() {
            return Ok(true);
        }
        let id = read_id(&self.state.submission_file(entry, "id")).context("an in-flight entry without its id")?;
        loop {
            let submission = self.submission(id).await?;
            if !matches!(submission["state"].as_str(), Some("queued" | "running")) {
                dsrl_pipeline::write_atomically(&json, serde_json::to_string_pretty(&submission)?.as_bytes())?;
                return Ok(true);
            }
            if wait == Wait::Look {
                return Ok(false);
            }
            tokio::time::sleep(WAIT_POLL).await;
        }
    }

    /// A submission as the server shows it, asked again while the server answers "not now" (within `PATIENCE`).
    async fn submission(&self, id: i64) -> Result<serde_json::Value, ClientError> {
        let started = std::time::Instant::now();
        loop {
            match self.client.submission(id).await {
                Err(e) if transient(&e) && started.elapsed() < PATIENCE => {
                    eprintln!("submission {id}: the server cannot answer now ({e}); asking again");
                    tokio::time::sleep(WAIT_POLL).await;
                }
                answer => return answer,
            }
        }
    }

    /// Whether a scoring failed for the service's sake and the entry is to be submitted again. A failure the
    /// leaderboard puts down to the checkpoint would come again (and the server refuses the same checkpoint while
    /// that submission stands): the run stops with its reason.
    fn failed_scoring(&self, entry: &EntryKey) -> anyhow::Result<bool> {
        let submission: serde_json::Value =
            serde_json::from_slice(&std::fs::read(self.state.submission_file(entry, "json"))?)?;
        if submission["state"] != "failed" {
            return Ok(false);
        }
        eprintln!(
            "{entry} submission {} failed: {}",
            submission["id"],
            submission["reason"].as_str().unwrap_or("no reason given")
        );
        anyhow::ensure!(
            submission["failure"] != "checkpoint",
            "the leaderboard failed {entry} as the checkpoint's fault: not submitted again"
        );
        let retries_file = self.state.submission_file(entry, "retries");
        let tries = std::fs::read_to_string(&retries_file)
            .ok()
            .and_then(|t| t.trim().parse::<u32>().ok())
            .unwrap_or(0)
            + 1;
        anyhow::ensure!(tries <= RETRIES, "giving up on {entry} after {tries} failed scorings");
        dsrl_pipeline::write_atomically(&retries_file, tries.to_string().as_bytes())?;
        self.state.forget_submission(entry)?;
        Ok(true)
    }

    /// Writes a scored entry into the results file, once per scoring (`dsrl-train reference-entry` replaces the line
    /// of the same task, method and seed).
    fn record(&mut self, entry: &EntryKey) -> anyhow::Result<()> {
        let json = self.state.submission_file(entry, "json");
        let mark = self.state.submission_file(entry, "recorded");
        if newer(&mark, &json) {
            return Ok(());
        }
        let status = reference_entry(&self.train, &self.state, entry, &self.results, Some(&json))?;
        anyhow::ensure!(status.success(), "recording {entry} failed ({status})");
        std::fs::write(&mark, b"")?;
        self.recorded += 1;
        Ok(())
    }
}

/// `dsrl-train reference-entry` for an entry's model: with `submission` (its final answer), the entry's line in
/// `results`; without (`--reproduce`), the check that its retrained checkpoints are the scored ones, renewing its
/// training record when they are.
pub fn reference_entry(
    train: &std::path::Path,
    state: &StateDir,
    entry: &EntryKey,
    results: &std::path::Path,
    submission: Option<&std::path::Path>,
) -> anyhow::Result<std::process::ExitStatus> {
    let mut command = std::process::Command::new(train);
    command.arg("reference-entry");
    match submission {
        Some(json) => command.arg("--submission").arg(json),
        None => command.arg("--reproduce"),
    };
    command
        .arg("--model")
        .arg(state.model_dir(entry))
        .arg("--method")
        .arg(entry.method.name())
        .arg("--results")
        .arg(results)
        .status()
        .with_context(|| format!("running {}", train.display()))
}

fn read_id(path: &std::path::Path) -> Option<i64> {
    std::fs::read_to_string(path).ok()?.trim().parse().ok()
}
