//! A submission's checkpoint files, checked completely before anything is stored or queued: names, sizes, the
//! format, the declared task and dimensions against the catalog, the weights against the declared architecture
//! (by building the network), and which cost thresholds the checkpoints cover.
//!
//! A submission is either one checkpoint scored at each of the task's three thresholds (`policy.json` +
//! `policy.safetensors`: unconditioned, or conditioned on the threshold — `target_cost`, `returns_to_go`) or one
//! checkpoint per threshold in folders (`<slot>/policy.json`, ...), each declaring
//! `conditioning = {kind = "per_threshold", cost_threshold = K}`, together covering exactly the task's thresholds.

use std::collections::BTreeMap;

use bytes::Bytes;
use dsrl_policy::Policy;
use dsrl_policy::checkpoint::{self, Conditioning, PolicyConfig};
use dsrl_suite::catalog::Task;
use serde::{Deserialize, Serialize};

use dsrl_service::error::ApiError;

/// One checkpoint of a submission, checked.
pub struct CheckedCheckpoint {
    /// The folder it came in (`""` for a single checkpoint at the top).
    pub slot: String,
    pub config: PolicyConfig,
    pub config_bytes: Bytes,
    pub weights_bytes: Bytes,
}

/// What a stored submission records of each checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointRecord {
    pub slot: String,
    /// `None`: scored at every threshold of the task.
    pub cost_threshold: Option<f64>,
    pub architecture: String,
    /// Object-store keys.
    pub config_key: String,
    pub weights_key: String,
}

/// A submission's checkpoints, in threshold order, and the digest that identifies them.
pub struct CheckedSubmission {
    pub checkpoints: Vec<CheckedCheckpoint>,
    /// [`checkpoint::submission_digest`]: the same network submitted twice has the same digest, whatever the JSON's
    /// formatting or training record.
    pub sha256: String,
}

impl CheckedSubmission {
    /// The dataset version the checkpoints say they were trained on (`training.dataset_version` in policy.json,
    /// which `dsrl-train` always writes): `None` when none says; the distinct versions joined by `,` when they
    /// differ.
    pub fn dataset_version(&self) -> Option<String> {
        let mut versions: Vec<&str> = Vec::new();
        for c in &self.checkpoints {
            let said = c
                .config
                .training
                .as_ref()
                .and_then(|t| t.get("dataset_version"))
                .and_then(|v| v.as_str());
            if let Some(v) = said
                && !versions.contains(&v)
            {
                versions.push(v);
            }
        }
        (!versions.is_empty()).then(|| versions.join(","))
    }
}

/// Largest slot name, and the characters allowed in it.
const MAX_SLOT_CHARS: usize = 64;

fn valid_slot(slot: &str) -> bool {
    !slot.is_empty()
        && slot.len() <= MAX_SLOT_CHARS
        && slot != "."
        && slot != ".."
        && slot
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
}

/// Splits an uploaded file's name into (slot, file); `None` when it is not a checkpoint file name.
fn split_name(name: &str) -> Option<(&str, &str)> {
    let (slot, file) = match name.split_once('/') {
        Some((slot, file)) if valid_slot(slot) => (slot, file),
        Some(_) => return None,
        None => ("", name),
    };
    (file == checkpoint::CONFIG_FILE || file == checkpoint::WEIGHTS_FILE).then_some((slot, file))
}

/// The limit for one uploaded file, by its name; `None` for a name that is not a checkpoint file.
pub fn file_limit(name: &str) -> Option<u64> {
    let (_, file) = split_name(name)?;
    Some(if file == checkpoint::CONFIG_FILE {
        checkpoint::MAX_CONFIG_BYTES
    } else {
        checkpoint::MAX_WEIGHTS_BYTES
    })
}

/// What scoring one submission may cost in all.
pub struct JobBudget {
    pub episodes_per_threshold: u32,
    pub max_multiply_adds: u64,
}

impl JobBudget {
    /// Refuses a checkpoint whose scoring would take more than the budget: its cost per action × the task's horizon
    /// × the episodes it plays (per threshold; each threshold for a checkpoint scored at all of them).
    fn check(&self, task: &Task, config: &PolicyConfig, thresholds: usize) -> Result<(), ApiError> {
        let per_action = config.step_cost().multiply_adds;
        let actions = u64::from(task.max_episode_steps) * u64::from(self.episodes_per_threshold) * thresholds as u64;
        let total = per_action.saturating_mul(actions);
        if total > self.max_multiply_adds {
            return Err(ApiError::InvalidArgument(format!(
                "scoring this {} would take up to {total} multiply-adds ({per_action} per action × {actions} actions: \
                 {} steps × {} episodes × {thresholds} thresholds); a submission's budget is {} \
                 (leaderboard.max_job_multiply_adds): use a smaller network or context",
                config.architecture.name(),
                task.max_episode_steps,
                self.episodes_per_threshold,
                self.max_multiply_adds
            )));
        }
        Ok(())
    }
}

/// Checks uploaded `(name, bytes)` files as a submission for `task`, within `budget`.
pub fn check(task: &Task, files: Vec<(String, Bytes)>, budget: &JobBudget) -> Result<CheckedSubmission, ApiError> {
    let bad = |m: String| ApiError::InvalidArgument(m);
    let mut slots: BTreeMap<String, (Option<Bytes>, Option<Bytes>)> = BTreeMap::new();
    for (name, bytes) in files {
        let Some((slot, file)) = split_name(&name) else {
            return Err(bad(format!(
                "unexpected file {name:?}: a submission holds policy.json and policy.safetensors, at the top or in \
                 one folder per cost threshold (<folder>/policy.json; folder names use letters, digits, . _ -)"
            )));
        };
        let entry = slots.entry(slot.to_owned()).or_default();
        let place = if file == checkpoint::CONFIG_FILE {
            &mut entry.0
        } else {
            &mut entry.1
        };
        if place.replace(bytes).is_some() {
            return Err(bad(format!("{name} was sent twice")));
        }
    }
    if slots.is_empty() {
        return Err(bad("the submission holds no checkpoint files".into()));
    }
    if slots.contains_key("") && slots.len() > 1 {
        return Err(bad(
            "a submission is either one checkpoint at the top or one per threshold in folders, not both".into(),
        ));
    }
    let mut checkpoints = Vec::new();
    for (slot, (config_bytes, weights_bytes)) in slots {
        let at = if slot.is_empty() {
            String::new()
        } else {
            format!("{slot}/")
        };
        let config_bytes = config_bytes.ok_or_else(|| bad(format!("{at}policy.json is missing")))?;
        let weights_bytes = weights_bytes.ok_or_else(|| bad(format!("{at}policy.safetensors is missing")))?;
        let in_slot = |e: String| bad(if slot.is_empty() { e } else { format!("{slot}: {e}") });
        let config = checkpoint::parse_config(&config_bytes).map_err(|e| in_slot(e.to_string()))?;
        dsrl_evaluation::evaluator::check_policy(task, &config).map_err(|e| in_slot(e.to_string()))?;
        let tensors = checkpoint::parse_weights(&weights_bytes).map_err(|e| in_slot(e.to_string()))?;
        // Building the network checks every tensor's presence and shape against the declared architecture.
        Policy::load(&config, &tensors).map_err(|e| in_slot(e.to_string()))?;
        checkpoints.push(CheckedCheckpoint {
            slot,
            config,
            config_bytes,
            weights_bytes,
        });
    }
    check_thresholds(task, &mut checkpoints)?;
    for c in &checkpoints {
        let thresholds = if c.config.conditioning.cost_threshold().is_some() {
            1
        } else {
            task.cost_thresholds.len()
        };
        budget.check(task, &c.config, thresholds).map_err(|e| {
            ApiError::InvalidArgument(format!(
                "{}{e}",
                if c.slot.is_empty() {
                    String::new()
                } else {
                    format!("{}: ", c.slot)
                }
            ))
        })?;
    }
    let sha256 = checkpoint::submission_digest(
        &checkpoints
            .iter()
            .map(|c| (&c.config, &c.weights_bytes[..]))
            .collect::<Vec<_>>(),
    );
    Ok(CheckedSubmission { checkpoints, sha256 })
}

/// One unconditioned checkpoint, or per-threshold checkpoints covering exactly the task's thresholds (sorted).
fn check_thresholds(task: &Task, checkpoints: &mut [CheckedCheckpoint]) -> Result<(), ApiError> {
    let thresholds = &task.cost_thresholds;
    let listed = thresholds.iter().map(|t| t.to_string()).collect::<Vec<_>>().join(", ");
    // One checkpoint scored at every threshold: unconditioned, or conditioned on the threshold it is scored at
    // (`check_policy` has checked that a returns-to-go policy has a target for each).
    if let [only] = checkpoints
        && only.config.conditioning.cost_threshold().is_none()
    {
        return Ok(());
    }
    let mut declared = Vec::new();
    for c in checkpoints.iter() {
        match c.config.conditioning {
            Conditioning::Unconditioned
            | Conditioning::TargetCost
            | Conditioning::ReturnsToGo { .. }
            | Conditioning::CostBudget => {
                return Err(ApiError::InvalidArgument(format!(
                    "{}: a checkpoint scored at every threshold ({} conditioning) must be the submission's only \
                     one; per-threshold checkpoints declare conditioning {{\"kind\": \"per_threshold\", \
                     \"cost_threshold\": K}} for K in {listed}",
                    c.slot,
                    c.config.conditioning.kind()
                )));
            }
            Conditioning::PerThreshold { cost_threshold } => {
                if !thresholds.contains(&cost_threshold) {
                    return Err(ApiError::InvalidArgument(format!(
                        "{}: cost threshold {cost_threshold} is not one of {}'s thresholds ({listed})",
                        if c.slot.is_empty() { "policy.json" } else { &c.slot },
                        task.id
                    )));
                }
                if declared.contains(&cost_threshold) {
                    return Err(ApiError::InvalidArgument(format!(
                        "two checkpoints are declared for cost threshold {cost_threshold}"
                    )));
                }
                declared.push(cost_threshold);
            }
        }
    }
    if let Some(missing) = dsrl_evaluation::evaluator::uncovered_thresholds(task, &declared) {
        return Err(ApiError::InvalidArgument(format!(
            "no checkpoint for cost threshold {missing} of {} (per-threshold submissions cover {listed})",
            task.id
        )));
    }
    // Every checkpoint here is per-threshold (checked above).
    let key = |c: &CheckedCheckpoint| c.cost_threshold().unwrap_or_default();
    checkpoints.sort_by(|a, b| key(a).total_cmp(&key(b)));
    Ok(())
}

impl CheckedCheckpoint {
    pub fn cost_threshold(&self) -> Option<f64> {
        self.config.conditioning.cost_threshold()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// FISOR's published configuration (`dsrl-train fisor`'s defaults) as a checkpoint declares it.
    fn fisor() -> checkpoint::Architecture {
        checkpoint::Architecture::Diffusion {
            time_dim: 64,
            cond_sizes: vec![128, 128],
            hidden_dim: 256,
            num_blocks: 3,
            layer_norm: true,
            critic_hidden_sizes: vec![256, 256],
            critic_members: 2,
            max_action: 1.0,
            sampler: checkpoint::DiffusionSampler::Ddpm {
                steps: 5,
                beta_min: 0.1,
                beta_max: 10.0,
                clip: true,
                temperature: 1.0,
                candidates: 16,
                choice: dsrl_policy::diffusion::CandidateChoice::MinCostQ,
            },
        }
    }

    #[test]
    fn the_default_budget_admits_fisor_at_its_published_settings_on_every_task() {
        let defaults = dsrl_service::config::LeaderboardConfig::default();
        let budget = JobBudget {
            episodes_per_threshold: defaults.episodes_per_threshold,
            max_multiply_adds: defaults.max_job_multiply_adds,
        };
        let catalog = dsrl_suite::Catalog::embedded().unwrap();
        let mut largest = 0;
        for task in catalog.tasks() {
            let config = PolicyConfig {
                format: checkpoint::FORMAT.into(),
                task: task.id.to_string(),
                obs_dim: task.obs_dim as usize,
                act_dim: task.act_dim as usize,
                architecture: fisor(),
                observation_normalization: None,
                conditioning: Conditioning::Unconditioned,
                training: None,
            };
            config
                .architecture
                .check_step_cost(config.obs_dim, config.act_dim)
                .unwrap();
            budget.check(task, &config, task.cost_thresholds.len()).unwrap();
            let per_action = config
                .architecture
                .step_cost(config.obs_dim, config.act_dim)
                .multiply_adds;
            largest = largest.max(per_action * u64::from(task.max_episode_steps) * 60);
        }
        // The comment on the default names this figure.
        assert!((8_000_000_000_000..8_500_000_000_000).contains(&largest), "{largest}");
    }

    #[test]
    fn file_names_are_a_checkpoint_at_the_top_or_in_safe_folders() {
        assert_eq!(split_name("policy.json"), Some(("", "policy.json")));
        assert_eq!(
            split_name("k10/policy.safetensors"),
            Some(("k10", "policy.safetensors"))
        );
        assert_eq!(split_name("../policy.json"), None);
        assert_eq!(split_name("a/b/policy.json"), None);
        assert_eq!(split_name("a b/policy.json"), None);
        assert_eq!(split_name("model.pt"), None);
        assert_eq!(file_limit("policy.json"), Some(checkpoint::MAX_CONFIG_BYTES));
        assert_eq!(file_limit("x/policy.safetensors"), Some(checkpoint::MAX_WEIGHTS_BYTES));
    }
}
