//! The training pool: every model of a run as one `dsrl-train` process, `jobs` at a time, task after task, so a
//! task's last models train beside the next task's first and no core waits for a task to finish.
//!
//! A model that finishes leaves its marker (`state.rs`); one that fails leaves none and stops new models from
//! starting, while those already training finish (their work is kept) before the run fails. Children die with the
//! run: dropped (an error, a signal) they are killed, and the kernel kills them if this process dies first.

use std::path::PathBuf;
use std::process::Stdio;

use tokio::process::{Child, Command};

use crate::plan::Method;
use crate::state::{EntryKey, StateDir};

/// One model to train.
#[derive(Debug, Clone)]
pub struct Model {
    pub entry: EntryKey,
    /// The benchmark threshold of a per-threshold method's model.
    pub threshold: Option<f64>,
    pub steps: u64,
    pub batch: Option<usize>,
    /// `cuda:N`, or the CPU.
    pub device: Option<String>,
    /// The dataset version the phase trains on (the task's starter or committed full build).
    pub dataset_version: String,
}

impl Model {
    fn command(&self, train: &std::path::Path, server: &str, state: &StateDir) -> Command {
        let mut command = Command::new(train);
        command
            .args(self.entry.method.train_command())
            .arg("--task")
            .arg(&self.entry.task)
            .arg("--server")
            .arg(server)
            .arg("--seed")
            .arg(self.entry.seed.to_string())
            .arg("--out")
            .arg(state.seed_dir(&self.entry.task, self.entry.seed))
            .arg("--steps")
            .arg(self.steps.to_string());
        if let Some(batch) = self.batch {
            command.arg("--batch-size").arg(batch.to_string());
        }
        if let Some(threshold) = self.threshold {
            command.arg("--cost-threshold").arg(threshold.to_string());
        }
        if let Some(device) = &self.device {
            command.arg("--device").arg(device);
        }
        command
            .stdin(Stdio::null())
            .stdout(Stdio::inherit())
            .stderr(Stdio::inherit());
        command
    }

    pub fn marker(&self, state: &StateDir) -> PathBuf {
        state.marker(&self.entry, self.threshold, self.steps, self.batch)
    }

    /// The entry, and the threshold where the method trains one model per threshold.
    fn label(&self) -> String {
        match self.threshold {
            Some(t) => format!("{} (threshold {t})", self.entry),
            None => self.entry.to_string(),
        }
    }

    /// Trained at this budget and on this dataset version: a model trained on another version of the task's data
    /// (a full build recorded again, a starter cut again) is stale whatever its marker says.
    pub fn is_trained(&self, state: &StateDir) -> bool {
        self.marker(state).exists()
            && state.trained_on(&self.entry, self.threshold).as_deref() == Some(self.dataset_version.as_str())
    }
}

/// Spawns a child that cannot outlive this process: killed when its handle is dropped, and sent SIGKILL by the
/// kernel when this process dies (`PR_SET_PDEATHSIG`; the runtime's worker threads live as long as the process).
pub fn spawn_supervised(command: &mut Command) -> std::io::Result<Child> {
    command.kill_on_drop(true);
    // SAFETY: prctl is async-signal-safe and touches only the child's own state between fork and exec.
    unsafe {
        command.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    command.spawn()
}

/// The pool's progress, looked at once a second by the run.
pub struct Pool {
    waiting: std::collections::VecDeque<Model>,
    running: Vec<(Model, Child)>,
    jobs: usize,
    train: PathBuf,
    server: String,
    state: StateDir,
    failed: Vec<String>,
    pub trained: u64,
    pub total: u64,
}

impl Pool {
    pub fn new(models: Vec<Model>, jobs: usize, train: PathBuf, server: String, state: StateDir) -> Pool {
        let total = models.len() as u64;
        Pool {
            waiting: models.into(),
            running: Vec::new(),
            jobs,
            train,
            server,
            state,
            failed: Vec::new(),
            trained: 0,
            total,
        }
    }

    /// Reaps finished models and starts waiting ones into free slots (none once a model failed). Returns whether
    /// anything is still training.
    pub fn step(&mut self) -> anyhow::Result<bool> {
        let mut i = 0;
        while i < self.running.len() {
            match self.running[i].1.try_wait()? {
                None => i += 1,
                Some(status) => {
                    let (model, _) = self.running.swap_remove(i);
                    if status.success() {
                        self.state.remove_markers(&model.entry, model.threshold)?;
                        std::fs::write(model.marker(&self.state), b"")?;
                        self.trained += 1;
                    } else {
                        let what = model.label();
                        eprintln!("{what} failed to train ({status})");
                        self.failed.push(what);
                    }
                }
            }
        }
        while self.failed.is_empty() && self.running.len() < self.jobs {
            let Some(model) = self.waiting.pop_front() else { break };
            if model.is_trained(&self.state) {
                self.trained += 1;
                continue;
            }
            if model.marker(&self.state).exists() {
                match self.state.trained_on(&model.entry, model.threshold) {
                    Some(_) => eprintln!(
                        "{} was trained on another dataset version than {}: trained again",
                        model.label(),
                        &model.dataset_version[..12.min(model.dataset_version.len())]
                    ),
                    None => eprintln!(
                        "{}: its checkpoint is gone (marked trained): trained again",
                        model.label()
                    ),
                }
                self.state.remove_markers(&model.entry, model.threshold)?;
            }
            let mut command = model.command(&self.train, &self.server, &self.state);
            let child = spawn_supervised(&mut command)
                .map_err(|e| anyhow::anyhow!("starting {}: {e}", self.train.display()))?;
            self.running.push((model, child));
        }
        if self.running.is_empty() && !self.failed.is_empty() {
            anyhow::bail!(
                "{} model(s) failed to train: {}",
                self.failed.len(),
                self.failed.join(", ")
            );
        }
        Ok(!self.running.is_empty())
    }
}

/// Whether every model of `method` for `entry` is trained, at its budget and on its dataset version.
pub fn trained(models: &[Model], entry: &EntryKey, state: &StateDir) -> bool {
    models.iter().filter(|m| &m.entry == entry).all(|m| m.is_trained(state))
}

/// The models of an entry: one per threshold, or one.
pub fn models_of(method: Method, thresholds: &[f64]) -> Vec<Option<f64>> {
    if method.per_threshold() {
        thresholds.iter().map(|&t| Some(t)).collect()
    } else {
        vec![None]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_model_trained_on_another_dataset_version_is_not_trained() {
        let dir = tempfile::tempdir().unwrap();
        let state = StateDir::new(dir.path().to_owned(), false);
        let model = Model {
            entry: EntryKey {
                task: "OfflineBallRun-v0".into(),
                seed: 0,
                method: Method::BcSafe,
            },
            threshold: Some(20.0),
            steps: 100,
            batch: None,
            device: None,
            dataset_version: "a".repeat(64),
        };
        let checkpoint = state.model_dir(&model.entry).join("threshold-20");
        std::fs::create_dir_all(&checkpoint).unwrap();
        let record = |version: &str| serde_json::json!({"training": {"dataset_version": version}}).to_string();
        std::fs::write(checkpoint.join("policy.json"), record(&"a".repeat(64))).unwrap();
        assert!(!model.is_trained(&state), "no marker yet");
        std::fs::write(model.marker(&state), b"").unwrap();
        assert!(model.is_trained(&state));
        assert!(trained(std::slice::from_ref(&model), &model.entry, &state));
        // The task's data was built again: the same marker, another version.
        std::fs::write(checkpoint.join("policy.json"), record(&"b".repeat(64))).unwrap();
        assert!(!model.is_trained(&state));
        assert!(!trained(std::slice::from_ref(&model), &model.entry, &state));
    }
}
