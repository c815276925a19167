//! `dsrl-train reference-entry`: one line of the reference results file (`dsrl_scoring::reference`) from a trained
//! model folder and the leaderboard's answer for its scored submission. Everything it writes is read from those
//! two: the budget, seed, dataset version and code commit from each model's `policy.json` training record; the
//! checkpoint digest, protocol version, scoring times and every episode from the submission. The pairing holds only
//! when the folder's checkpoints have the digest the submission scored.
//!
//! It also re-records an entry for its model trained again from scratch (`reproduce`): the same digest means the
//! same networks, so the scoring stands and the entry names the commit that reproduced them.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail, ensure};
use dsrl_policy::checkpoint::{self, CONFIG_FILE};
use dsrl_scoring::reference::{
    REFERENCE_METHODS, ReferenceEntry, ScoringRecord, TrainingBudget, osrl_budget, read_results, upsert, write_results,
};
use dsrl_suite::Catalog;
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
    cpu: Option<String>,
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
    /// The build that scored it (a server older than this record leaves it out).
    #[serde(default)]
    scored_by: Option<String>,
    episodes: Vec<EpisodeResult>,
}

/// The checkpoint folders of a model folder: itself, or one per threshold folder (those with a `policy.json`).
fn model_checkpoints(dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    if dir.join(CONFIG_FILE).is_file() {
        return Ok(vec![dir.to_owned()]);
    }
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join(CONFIG_FILE).is_file())
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

/// What a model folder says of itself: its checkpoints' common training record and the leaderboard's digest of them.
struct Model {
    task: String,
    /// One record per checkpoint (all of one budget, seed, dataset and commit).
    trainings: Vec<Training>,
    dataset_version: String,
    code_commit: String,
    digest: String,
}

impl Model {
    fn read(dir: &Path) -> anyhow::Result<Model> {
        let mut task = None;
        let mut trainings = Vec::new();
        let mut checkpoints = Vec::new();
        let slots = model_checkpoints(dir)?;
        // Each policy.json is read once, size-limited: its training record here, the whole of it for the digest.
        for slot in &slots {
            let (config, weights) =
                checkpoint::read_bytes(slot).with_context(|| format!("reading {}", slot.display()))?;
            let config_file = slot.join(CONFIG_FILE);
            ensure!(
                task.get_or_insert_with(|| config.task.clone()) == &config.task,
                "the models in {} are of different tasks",
                dir.display()
            );
            let training = config
                .training
                .clone()
                .with_context(|| format!("{}: no training record", config_file.display()))?;
            trainings.push(
                serde_json::from_value::<Training>(training)
                    .with_context(|| format!("{}: no readable training record", config_file.display()))?,
            );
            checkpoints.push((config, weights));
        }
        let first = &trainings[0];
        let same = |m: &Training| {
            (m.steps, m.batch_size, m.seed) == (first.steps, first.batch_size, first.seed)
                && m.dataset_version == first.dataset_version
                && m.code_commit == first.code_commit
        };
        if !trainings.iter().all(same) {
            // Named per folder, so the reader sees which to train again (typically those of another build,
            // when a release build was made while a long reference run went on).
            let each: Vec<String> = slots
                .iter()
                .zip(&trainings)
                .map(|(slot, m)| {
                    format!(
                        "{}: {} steps, batch {}, seed {}, dataset {}, code {}",
                        slot.file_name().unwrap_or_default().to_string_lossy(),
                        m.steps,
                        m.batch_size,
                        m.seed,
                        m.dataset_version.as_deref().map_or("none", |v| &v[..v.len().min(12)]),
                        m.code_commit.as_deref().unwrap_or("none"),
                    )
                })
                .collect();
            bail!(
                "the models in {} differ in budget, seed, dataset or code ({}); one entry is one training run: \
                 remove the folders that differ to train them again",
                dir.display(),
                each.join("; ")
            );
        }
        let Some(dataset_version) = first.dataset_version.clone() else {
            bail!("{}: the training record names no dataset version", dir.display())
        };
        let Some(code_commit) = first.code_commit.clone() else {
            bail!(
                "{}: the training record names no code commit (trained by an older dsrl-train)",
                dir.display()
            )
        };
        let digest = checkpoint::submission_digest(&checkpoints.iter().map(|(c, w)| (c, &w[..])).collect::<Vec<_>>());
        Ok(Model {
            task: task.context("a model folder holds a checkpoint")?,
            trainings,
            dataset_version,
            code_commit,
            digest,
        })
    }

    /// The CPU the models trained on, when every training record names it (each distinct one, joined by " + ").
    fn cpu(&self) -> Option<String> {
        let mut cpus = self
            .trainings
            .iter()
            .map(|m| m.cpu.clone())
            .collect::<Option<Vec<String>>>()?;
        cpus.sort_unstable();
        cpus.dedup();
        Some(cpus.join(" + "))
    }

    fn budget(&self, dir: &Path, method: &str, task: &dsrl_suite::Task) -> anyhow::Result<TrainingBudget> {
        let first = &self.trainings[0];
        let (osrl_steps, osrl_batch_size) = osrl_budget(method, task).context("a reference method has a budget")?;
        Ok(TrainingBudget {
            steps: first.steps,
            batch_size: first.batch_size,
            models: self.trainings.len() as u32,
            seconds: self.trainings.iter().map(|m| m.seconds).sum(),
            cpu_seconds: self
                .trainings
                .iter()
                .map(|m| m.cpu_seconds)
                .sum::<Option<f64>>()
                .with_context(|| {
                    format!(
                        "{}: a training record has no cpu_seconds (an older dsrl-train)",
                        dir.display()
                    )
                })?,
            cpu: self.cpu(),
            osrl_steps,
            osrl_batch_size,
        })
    }
}

fn known_method(method: &str) -> anyhow::Result<()> {
    ensure!(
        REFERENCE_METHODS.contains(&method),
        "unknown method {method:?}; reference methods are {}",
        REFERENCE_METHODS.join(", ")
    );
    Ok(())
}

/// Puts `entry` into `results` in place of any entry of the same (task, method, seed); the file is checked by
/// reading it back, then replaced atomically. Two writers (a sweep recording scorings beside a reproduction) take
/// turns on a lock file beside it, so neither writes over the other's entry.
fn write_entry(results: &Path, entry: ReferenceEntry, catalog: &Catalog) -> anyhow::Result<()> {
    let lock_path = results.with_extension("jsonl.lock");
    let lock = std::fs::File::create(&lock_path).with_context(|| format!("creating {}", lock_path.display()))?;
    lock.lock()
        .with_context(|| format!("locking {}", lock_path.display()))?;
    let mut entries = if results.exists() {
        read_results(&std::fs::read_to_string(results)?, catalog)?
    } else {
        Vec::new()
    };
    upsert(&mut entries, entry);
    let text = write_results(&entries);
    read_results(&text, catalog)?;
    let tmp = results.with_extension("jsonl.tmp");
    std::fs::write(&tmp, text).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, results).with_context(|| format!("replacing {}", results.display()))?;
    Ok(())
}

/// Builds the entry of `method` from `model` and the submission JSON at `submission`, and writes it into `results`
/// in place of any entry of the same (task, method, seed).
pub fn record(model: &Path, submission: &Path, method: &str, results: &Path) -> anyhow::Result<ReferenceEntry> {
    known_method(method)?;
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
    let read = Model::read(model)?;
    // A submission id kept from another scoring server's database names someone else's submission.
    ensure!(
        read.task == view.task,
        "{} is a model of {}, but submission {} scored {}: the submission is not this model's",
        model.display(),
        read.task,
        view.id,
        view.task
    );
    // The entry pairs this folder's training record with that submission's episodes: only when the submission
    // scored exactly these networks (a model trained again since, to other weights, is not the one scored).
    ensure!(
        read.digest == view.checkpoint_sha256,
        "{} holds checkpoints of digest {}, but submission {} scored {}: the model is not the one scored \
         (trained again since?)",
        model.display(),
        read.digest,
        view.id,
        view.checkpoint_sha256
    );
    let (started_at, finished_at) = (
        view.started_at.clone().context("no start time")?,
        view.finished_at.clone().context("no finish time")?,
    );
    let entry = ReferenceEntry {
        task: view.task.clone(),
        method: method.to_owned(),
        seed: read.trainings[0].seed,
        training: read.budget(model, method, task)?,
        dataset_version: read.dataset_version,
        code_commit: read.code_commit,
        checkpoint_sha256: view.checkpoint_sha256.clone(),
        protocol_version,
        scoring: ScoringRecord {
            submission: view.id,
            seconds: seconds_between(&started_at, &finished_at)?,
            started_at,
            finished_at,
            build: view.scored_by,
        },
        episodes: view.episodes,
    };
    write_entry(results, entry.clone(), &catalog)?;
    Ok(entry)
}

/// Re-records the entry of `method` already in `results` for `model`, a folder trained again from scratch: when
/// its checkpoints have the digest the entry was scored with, and the same budget, seed and dataset, the networks
/// are the ones scored, so the entry takes the new training record (its code commit, its seconds) and keeps its
/// scoring and episodes. Otherwise the entry is left as it is and the difference is the error.
pub fn reproduce(model: &Path, method: &str, results: &Path) -> anyhow::Result<ReferenceEntry> {
    known_method(method)?;
    let catalog = Catalog::embedded()?;
    let read = Model::read(model)?;
    let task = catalog.get(&read.task)?;
    let seed = read.trainings[0].seed;
    let entries = read_results(
        &std::fs::read_to_string(results).with_context(|| format!("reading {}", results.display()))?,
        &catalog,
    )?;
    let Some(old) = entries
        .into_iter()
        .find(|e| (e.task.as_str(), e.method.as_str(), e.seed) == (task.id.as_str(), method, seed))
    else {
        bail!(
            "{} holds no {method} entry of {} seed {seed} to reproduce",
            results.display(),
            task.id
        )
    };
    let training = read.budget(model, method, task)?;
    ensure!(
        (training.steps, training.batch_size, training.models)
            == (old.training.steps, old.training.batch_size, old.training.models),
        "{} was trained for {} steps at batch {} ({} models), the entry for {} at batch {} ({} models)",
        model.display(),
        training.steps,
        training.batch_size,
        training.models,
        old.training.steps,
        old.training.batch_size,
        old.training.models
    );
    ensure!(
        read.dataset_version == old.dataset_version,
        "{} was trained on dataset version {}, the entry on {}",
        model.display(),
        read.dataset_version,
        old.dataset_version
    );
    ensure!(
        read.digest == old.checkpoint_sha256,
        "not reproduced: {} trained again by {} holds checkpoints of digest {}, but the entry (trained by {}) \
         scored {}",
        model.display(),
        read.code_commit,
        read.digest,
        old.code_commit,
        old.checkpoint_sha256
    );
    // Checked last, so a working tree's build still shows whether the networks came out the same.
    ensure!(
        !read.code_commit.ends_with("-modified"),
        "{} reproduced the scored networks (digest {}), but it was trained by a dsrl-train built from uncommitted \
         sources ({}): a reproduction names a commit anyone can build, so the entry is left as it is",
        model.display(),
        read.digest,
        read.code_commit
    );
    let entry = ReferenceEntry {
        training,
        code_commit: read.code_commit,
        ..old
    };
    write_entry(results, entry.clone(), &catalog)?;
    Ok(entry)
}

#[cfg(test)]
mod tests {
    use super::*;
    use dsrl_policy::checkpoint::{Architecture, Conditioning, FORMAT, PolicyConfig, WEIGHTS_FILE};
    use dsrl_policy::mlp::Activation;

    /// A BC-Safe-like model folder on BallRun: one checkpoint per threshold, each with its training record.
    fn model(dir: &Path, weights: &[u8]) {
        model_by(dir, weights, "0123456789ab", 3)
    }

    fn model_by(dir: &Path, weights: &[u8], commit: &str, steps: u64) {
        for threshold in [10.0, 20.0, 40.0] {
            let slot = dir.join(format!("threshold-{threshold}"));
            std::fs::create_dir_all(&slot).unwrap();
            let config = PolicyConfig {
                format: FORMAT.into(),
                task: "OfflineBallRun-v0".into(),
                obs_dim: 7,
                act_dim: 2,
                architecture: Architecture::MlpActor {
                    hidden_sizes: vec![4],
                    activation: Activation::Relu,
                    max_action: 1.0,
                },
                observation_normalization: None,
                conditioning: Conditioning::PerThreshold {
                    cost_threshold: threshold,
                },
                training: Some(serde_json::json!({
                    "steps": steps, "batch_size": 16, "seed": 0, "dataset_version": "ab".repeat(32),
                    "code_commit": commit, "seconds": 1.5, "cpu_seconds": 1.25, "cpu": "Test CPU, AVX-512: no",
                })),
            };
            std::fs::write(slot.join(CONFIG_FILE), serde_json::to_vec_pretty(&config).unwrap()).unwrap();
            std::fs::write(slot.join(WEIGHTS_FILE), weights).unwrap();
        }
    }

    fn submission(path: &Path, checkpoint_sha256: &str) {
        let episodes: Vec<_> = [10.0, 20.0, 40.0]
            .iter()
            .map(|&t| {
                serde_json::json!({"cost_threshold": t, "episode": 0, "reward_return": 100.0, "cost_return": 5.0,
                                   "length": 100})
            })
            .collect();
        let view = serde_json::json!({
            "id": 7, "task": "OfflineBallRun-v0", "state": "finished", "checkpoint_sha256": checkpoint_sha256,
            "protocol_version": "p1.test", "started_at": "2026-11-27T07:00:00Z",
            "finished_at": "2026-11-27T07:01:30Z", "episodes": episodes,
        });
        std::fs::write(path, serde_json::to_vec(&view).unwrap()).unwrap();
    }

    /// The digest the leaderboard gives the folder's checkpoints (the same function the server calls).
    fn digest_of(dir: &Path) -> String {
        let read: Vec<_> = ["threshold-40", "threshold-10", "threshold-20"]
            .iter()
            .map(|slot| checkpoint::read_bytes(&dir.join(slot)).unwrap())
            .collect();
        checkpoint::submission_digest(&read.iter().map(|(c, w)| (c, &w[..])).collect::<Vec<_>>())
    }

    fn entries_in(results: &Path) -> Vec<ReferenceEntry> {
        read_results(
            &std::fs::read_to_string(results).unwrap(),
            &Catalog::embedded().unwrap(),
        )
        .unwrap()
    }

    /// A model of `weights` in `dir`/scored, scored and recorded in `dir`/results.jsonl.
    fn recorded(dir: &Path, weights: &[u8]) -> (PathBuf, PathBuf, ReferenceEntry) {
        let scored = dir.join("scored");
        model(&scored, weights);
        let sub = dir.join("sub.json");
        submission(&sub, &digest_of(&scored));
        let results = dir.join("results.jsonl");
        let entry = record(&scored, &sub, "BC-Safe", &results).unwrap();
        (scored, results, entry)
    }

    #[test]
    fn an_entry_pairs_a_model_only_with_the_submission_that_scored_it() {
        let dir = tempfile::tempdir().unwrap();
        let (scored, retrained) = (dir.path().join("scored"), dir.path().join("retrained"));
        model(&scored, b"the weights that were scored");
        model(&retrained, b"other weights, trained again");
        let sub = dir.path().join("sub.json");
        submission(&sub, &digest_of(&scored));
        let results = dir.path().join("results.jsonl");

        let refused = record(&retrained, &sub, "BC-Safe", &results).unwrap_err().to_string();
        assert!(refused.contains("is not the one scored"), "{refused}");
        assert!(!results.exists(), "a refused entry writes nothing");

        let entry = record(&scored, &sub, "BC-Safe", &results).unwrap();
        assert_eq!(entry.checkpoint_sha256, digest_of(&scored));
        assert_eq!((entry.training.models, entry.training.seconds), (3, 4.5));
        assert_eq!(entry.training.cpu.as_deref(), Some("Test CPU, AVX-512: no"));
        assert_eq!(entry.scoring.seconds, 90.0);
        assert_eq!(entries_in(&results), vec![entry]);
    }

    #[test]
    fn an_entry_takes_the_record_of_a_retraining_only_when_it_gives_the_networks_scored() {
        let dir = tempfile::tempdir().unwrap();
        let (_, results, first) = recorded(dir.path(), b"the weights that were scored");
        let text = std::fs::read_to_string(&results).unwrap();

        // Other weights, another budget, another method, a build of uncommitted sources: refused, the file untouched.
        let scored_weights: &[u8] = b"the weights that were scored";
        for (name, weights, commit, steps, method, refusal) in [
            (
                "other",
                &b"weights of another build"[..],
                "fedcba987654",
                3,
                "BC-Safe",
                "not reproduced",
            ),
            ("longer", scored_weights, "fedcba987654", 4, "BC-Safe", "4 steps"),
            ("scored", scored_weights, "0123456789ab", 3, "BC-All", "no BC-All entry"),
            (
                "dirty",
                scored_weights,
                "fedcba987654-modified",
                3,
                "BC-Safe",
                "uncommitted sources",
            ),
        ] {
            let again = dir.path().join(name);
            if name != "scored" {
                model_by(&again, weights, commit, steps);
            }
            let refused = reproduce(&again, method, &results).unwrap_err().to_string();
            assert!(refused.contains(refusal), "{name}: {refused}");
        }
        assert_eq!(std::fs::read_to_string(&results).unwrap(), text);

        // The same networks from another commit: the entry names that commit and keeps its scoring.
        let again = dir.path().join("again");
        model_by(&again, b"the weights that were scored", "fedcba987654", 3);
        let entry = reproduce(&again, "BC-Safe", &results).unwrap();
        assert_eq!(entry.code_commit, "fedcba987654");
        assert_eq!(
            ReferenceEntry {
                code_commit: first.code_commit.clone(),
                ..entry.clone()
            },
            first
        );
        assert_eq!(entries_in(&results), vec![entry]);
    }

    #[test]
    fn a_model_trained_by_two_builds_is_refused_naming_the_folders() {
        let dir = tempfile::tempdir().unwrap();
        let mixed = dir.path().join("mixed");
        model(&mixed, b"weights");
        // One threshold trained again by another build, as when a release build lands during a long run.
        let config = mixed.join("threshold-40").join(CONFIG_FILE);
        let text = std::fs::read_to_string(&config)
            .unwrap()
            .replace("0123456789ab", "fedcba987654");
        std::fs::write(&config, text).unwrap();
        let sub = dir.path().join("sub.json");
        submission(&sub, &digest_of(&mixed));
        let results = dir.path().join("results.jsonl");

        let refused = record(&mixed, &sub, "BC-Safe", &results).unwrap_err().to_string();
        assert!(refused.contains("differ in budget, seed, dataset or code"), "{refused}");
        assert!(
            refused.contains("threshold-40: 3 steps, batch 16, seed 0, dataset abababababab, code fedcba987654"),
            "{refused}"
        );
        assert!(
            refused.contains("threshold-10: 3 steps, batch 16, seed 0, dataset abababababab, code 0123456789ab"),
            "{refused}"
        );
        assert!(!results.exists(), "a refused entry writes nothing");
    }

    #[test]
    fn writers_at_once_lose_no_entry() {
        let dir = tempfile::tempdir().unwrap();
        let (_, results, entry) = recorded(dir.path(), b"weights");
        let catalog = Catalog::embedded().unwrap();
        std::thread::scope(|scope| {
            for writer in 0..4u64 {
                let (entry, results, catalog) = (&entry, &results, &catalog);
                scope.spawn(move || {
                    for i in 0..8 {
                        let seed = 1 + writer * 8 + i;
                        write_entry(results, ReferenceEntry { seed, ..entry.clone() }, catalog).unwrap();
                    }
                });
            }
        });
        assert_eq!(entries_in(&results).len(), 1 + 4 * 8);
    }
}
