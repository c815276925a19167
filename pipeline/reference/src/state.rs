//! Where a phase keeps its work, so that a killed run resumes: the models `dsrl-train` wrote, a marker per
//! finished model naming its budget, and per entry the submission made for it and its final answer. A marker counts
//! only while the model's checkpoint names the dataset version the phase trains on (`trained_on`): a task whose data
//! was built again has its models trained again.
//!
//! ```text
//! <state>/policies/<task>/seed-<s>/<method>/...                  dsrl-train's output (--reproduce: reproduced/policies)
//! <state>/policies/<task>/seed-<s>/.trained-<method>-<threshold or ->-steps-<n>-batch-<b or osrl>
//! <state>/submissions/<task>/seed-<s>/<method>.id | .json | .recorded | .retries
//! <state>/server/, server.log, user-token                         the private scoring server
//! ```

use std::path::{Path, PathBuf};

use crate::plan::Method;

/// One entry of the table: a method trained with a seed on a task.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EntryKey {
    pub task: String,
    pub seed: u64,
    pub method: Method,
}

impl std::fmt::Display for EntryKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} seed {}: {}", self.task, self.seed, self.method.name())
    }
}

#[derive(Debug, Clone)]
pub struct StateDir {
    pub root: PathBuf,
    policies: PathBuf,
}

impl StateDir {
    pub fn new(root: PathBuf, reproduce: bool) -> StateDir {
        let policies = if reproduce {
            root.join("reproduced/policies")
        } else {
            root.join("policies")
        };
        StateDir { root, policies }
    }

    /// Every model, by task and seed.
    pub fn policies(&self) -> &Path {
        &self.policies
    }

    /// `dsrl-train --out`: a seed's models of every method.
    pub fn seed_dir(&self, task: &str, seed: u64) -> PathBuf {
        self.policies.join(task).join(format!("seed-{seed}"))
    }

    /// The checkpoint folder submitted for an entry.
    pub fn model_dir(&self, entry: &EntryKey) -> PathBuf {
        self.seed_dir(&entry.task, entry.seed).join(entry.method.key())
    }

    /// The marker of a finished model: it names the budget, so a model trained to another budget is trained again.
    pub fn marker(&self, entry: &EntryKey, threshold: Option<f64>, steps: u64, batch: Option<usize>) -> PathBuf {
        let threshold = threshold.map_or("-".to_owned(), |t| t.to_string());
        let batch = batch.map_or("osrl".to_owned(), |b| b.to_string());
        self.seed_dir(&entry.task, entry.seed).join(format!(
            ".trained-{}-{threshold}-steps-{steps}-batch-{batch}",
            entry.method.key()
        ))
    }

    /// The dataset version a finished model trained on, as its checkpoint's training record names it
    /// (`<model>/policy.json`, or `<model>/threshold-<K>/policy.json` for a per-threshold method's); `None` where
    /// there is no readable record.
    pub fn trained_on(&self, entry: &EntryKey, threshold: Option<f64>) -> Option<String> {
        let mut dir = self.model_dir(entry);
        if let Some(t) = threshold {
            dir = dir.join(format!("threshold-{t}"));
        }
        let config: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join("policy.json")).ok()?).ok()?;
        config["training"]["dataset_version"].as_str().map(str::to_owned)
    }

    /// The markers of one model at any budget (removed before its new marker is written).
    pub fn remove_markers(&self, entry: &EntryKey, threshold: Option<f64>) -> std::io::Result<()> {
        let threshold = threshold.map_or("-".to_owned(), |t| t.to_string());
        let prefix = format!(".trained-{}-{threshold}-", entry.method.key());
        let dir = self.seed_dir(&entry.task, entry.seed);
        for found in std::fs::read_dir(&dir)? {
            let found = found?;
            if found.file_name().to_string_lossy().starts_with(&prefix) {
                std::fs::remove_file(found.path())?;
            }
        }
        Ok(())
    }

    /// `<state>/submissions/<task>/seed-<s>/<method>` plus `extension` (id, json, recorded, retries).
    pub fn submission_file(&self, entry: &EntryKey, extension: &str) -> PathBuf {
        self.root
            .join("submissions")
            .join(&entry.task)
            .join(format!("seed-{}", entry.seed))
            .join(format!("{}.{extension}", entry.method.key()))
    }

    /// Forgets an entry's submission (its id, final answer and recording mark), keeping its retry count.
    pub fn forget_submission(&self, entry: &EntryKey) -> std::io::Result<()> {
        for extension in ["id", "json", "recorded"] {
            remove_if_there(&self.submission_file(entry, extension))?;
        }
        Ok(())
    }
}

pub fn remove_if_there(path: &Path) -> std::io::Result<()> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
        _ => Ok(()),
    }
}

/// Whether `a` was modified after `b` (false when either is missing).
pub fn newer(a: &Path, b: &Path) -> bool {
    let modified = |p: &Path| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    matches!((modified(a), modified(b)), (Some(a), Some(b)) if a > b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn markers_keep_the_layout_the_state_folders_were_made_with() {
        let state = StateDir::new(PathBuf::from("/s"), false);
        let entry = EntryKey {
            task: "OfflineBallRun-v0".into(),
            seed: 0,
            method: Method::BcAll,
        };
        assert_eq!(
            state.marker(&entry, None, 3, None),
            Path::new("/s/policies/OfflineBallRun-v0/seed-0/.trained-bc-all---steps-3-batch-osrl")
        );
        let entry = EntryKey {
            method: Method::Bearl,
            ..entry
        };
        assert_eq!(
            state.marker(&entry, Some(40.0), 9, Some(16)),
            Path::new("/s/policies/OfflineBallRun-v0/seed-0/.trained-bearl-40-steps-9-batch-16")
        );
        assert_eq!(
            state.submission_file(&entry, "id"),
            Path::new("/s/submissions/OfflineBallRun-v0/seed-0/bearl.id")
        );
    }
}
