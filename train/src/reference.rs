//! `dsrl-train reference-entry`: one line of the reference results file (`dsrl_suite::reference`) from a trained
//! model folder and the leaderboard's answer for its scored submission. Everything it writes is read from those
//! two: the budget, seed, dataset version and code commit from each model's `policy.json` training record; the
//! checkpoint digest, protocol version, scoring times and every episode from the submission.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail, ensure};
use dsrl_policy::checkpoint::CONFIG_FILE;
use dsrl_suite::Catalog;
use dsrl_suite::reference::{
    REFERENCE_METHODS, ReferenceEntry, ScoringRecord, TrainingBudget, osrl_budget, read_results, upsert, write_results,
};
use dsrl_suite::score::EpisodeResult;
use serde::Deserialize;

/// What the entry needs of one model's training record.
#[derive(Deserialize)]
struct Training {
    steps: u64,
    batch_size: usize,
    seed: u64,
    dataset_version: Option<String>,
    code_commit: Option<String>,
    seconds: f64,
    cpu_seconds: Option<f64>,
}

#[derive(Deserialize)]
struct TrainingOnly {
    task: String,
    training: Option<Training>,
}

/// What the entry needs of the leaderboard's view of the submission (`GET /v1/submissions/{id}`).
#[derive(Deserialize)]
struct Submission {
    id: i64,
    task: String,
    state: String,
    checkpoint_sha256: String,
    protocol_version: Option<String>,
    started_at: Option<String>,
    finished_at: Option<String>,
    episodes: Vec<EpisodeResult>,
}

/// The `policy.json` files of a model folder: its own, or one per threshold folder.
fn model_configs(dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let top = dir.join(CONFIG_FILE);
    if top.is_file() {
        return Ok(vec![top]);
    }
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path().join(CONFIG_FILE)))
        .filter(|p| p.is_file())
        .collect();
    found.sort();
    ensure!(
        !found.is_empty(),
        "{} holds no policy.json (nor threshold folders with one)",
        dir.display()
    );
    Ok(found)
}

fn seconds_between(start: &str, end: &str) -> anyhow::Result<f64> {
    use time::format_description::well_known::Rfc3339;
    let parse = |s: &str| time::OffsetDateTime::parse(s, &Rfc3339).with_context(|| format!("time {s:?}"));
    Ok((parse(end)? - parse(start)?).as_seconds_f64())
}

/// Builds the entry of `method` from `model` and the submission JSON at `submission`, and writes it into `results`
/// in place of any entry of the same (task, method, seed); the file is replaced atomically.
pub fn record(model: &Path, submission: &Path, method: &str, results: &Path) -> anyhow::Result<ReferenceEntry> {
    ensure!(
        REFERENCE_METHODS.contains(&method),
        "unknown method {method:?}; reference methods are {}",
        REFERENCE_METHODS.join(", ")
    );
    let catalog = Catalog::embedded()?;
    let view: Submission = serde_json::from_slice(
        &std::fs::read(submission).with_context(|| format!("reading {}", submission.display()))?,
    )
    .with_context(|| format!("{} is not a submission's JSON", submission.display()))?;
    ensure!(
        view.state == "finished",
        "submission {} is {}, not finished",
        view.id,
        view.state
    );
    let task = catalog.get(&view.task)?;
    let protocol_version = view
        .protocol_version
        .clone()
        .with_context(|| format!("submission {} records no protocol version (an older server?)", view.id))?;
    let mut models = Vec::new();
    for path in model_configs(model)? {
        let parsed: TrainingOnly = serde_json::from_slice(&std::fs::read(&path)?)
            .with_context(|| format!("{}: no readable training record", path.display()))?;
        // A submission id kept from another scoring server's database names someone else's submission.
        ensure!(
            parsed.task == view.task,
            "{} is a model of {}, but submission {} scored {}: the submission is not this model's",
            path.display(),
            parsed.task,
            view.id,
            view.task
        );
        models.push(
            parsed
                .training
                .with_context(|| format!("{}: no training record", path.display()))?,
        );
    }
    let first = &models[0];
    for m in &models {
        ensure!(
            (m.steps, m.batch_size, m.seed) == (first.steps, first.batch_size, first.seed)
                && m.dataset_version == first.dataset_version
                && m.code_commit == first.code_commit,
            "the models in {} differ in budget, seed, dataset or code",
            model.display()
        );
    }
    let Some(dataset_version) = first.dataset_version.clone() else {
        bail!("{}: the training record names no dataset version", model.display())
    };
    let Some(code_commit) = first.code_commit.clone() else {
        bail!(
            "{}: the training record names no code commit (trained by an older dsrl-train)",
            model.display()
        )
    };
    let (osrl_steps, osrl_batch_size) = osrl_budget(method, task).context("a reference method has a budget")?;
    let (started_at, finished_at) = (
        view.started_at.clone().context("no start time")?,
        view.finished_at.clone().context("no finish time")?,
    );
    let entry = ReferenceEntry {
        task: view.task.clone(),
        method: method.to_owned(),
        seed: first.seed,
        training: TrainingBudget {
            steps: first.steps,
            batch_size: first.batch_size,
            models: models.len() as u32,
            seconds: models.iter().map(|m| m.seconds).sum(),
            cpu_seconds: models
                .iter()
                .map(|m| m.cpu_seconds)
                .sum::<Option<f64>>()
                .with_context(|| {
                    format!(
                        "{}: a training record has no cpu_seconds (an older dsrl-train)",
                        model.display()
                    )
                })?,
            osrl_steps,
            osrl_batch_size,
        },
        dataset_version,
        code_commit,
        checkpoint_sha256: view.checkpoint_sha256.clone(),
        protocol_version,
        scoring: ScoringRecord {
            submission: view.id,
            seconds: seconds_between(&started_at, &finished_at)?,
            started_at,
            finished_at,
        },
        episodes: view.episodes,
    };
    let mut entries = if results.exists() {
        read_results(&std::fs::read_to_string(results)?, &catalog)?
    } else {
        Vec::new()
    };
    upsert(&mut entries, entry.clone());
    let text = write_results(&entries);
    // Checked by reading it back before it replaces the file.
    read_results(&text, &catalog)?;
    let tmp = results.with_extension("jsonl.tmp");
    std::fs::write(&tmp, text).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, results).with_context(|| format!("replacing {}", results.display()))?;
    Ok(entry)
}
