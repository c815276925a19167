//! The protocol version: one string that names everything that makes two leaderboard results comparable (MLCommons
//! AlgoPerf's practice: results are compared only within one version). It is a digest of
//! - the catalog's scoring facts: every task's id, simulator, horizon, dimensions, normalization constants and cost
//!   thresholds;
//! - the simulator pins (the pinned requirements and the fixes applied to them);
//! - the episodes played per threshold;
//! - the scoring layout (environments per threshold, each playing several episodes in turn): on some tasks an
//!   environment's later episodes depend on its earlier ones (Bullet keeps motor targets across a reset), so another
//!   layout plays other episodes from the same seeds;
//! - the held-seed policy (how episode seeds are derived);
//! - the scorer's revision (bumped by hand when the scoring code changes what an episode scores; a drift test in
//!   `dsrl-evaluation` names the sources it covers),
//!
//! under a rules number (`RULES`) for changes none of those capture. Changing any part changes the version.

use serde::Serialize;
use sha2::{Digest, Sha256};

use dsrl_suite::catalog::Catalog;

/// The revision of the benchmark rules themselves (how scores are aggregated, what is safe, how entries rank).
pub const RULES: u32 = 1;

/// The scoring layout every result had before the layout entered the digest. It stays out of the digest's input, so
/// the versions of those results stand; any other layout enters it and gives another version.
pub const DEFAULT_ENVS_PER_SESSION: u32 = 5;

/// What the version is computed from.
#[derive(Debug, Clone)]
pub struct ProtocolParts<'a> {
    pub catalog: &'a Catalog,
    /// The simulator environment's pins and fixes, as text.
    pub simulator_pins: &'a str,
    pub episodes_per_threshold: u32,
    /// Environments per threshold while scoring (one session each).
    pub envs_per_session: u32,
    /// The held-seed policy's name.
    pub held_seeds: &'a str,
    pub scorer_revision: u32,
}

/// A protocol: its version and the summary of what it covers, as the leaderboard shows it.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct Protocol {
    /// `p<rules>.<first 10 hex digits of the digest>`.
    pub version: String,
    pub rules: u32,
    pub tasks: usize,
    /// sha256 of the catalog's scoring facts and of the simulator pins.
    pub catalog_sha256: String,
    pub simulator_pins_sha256: String,
    pub episodes_per_threshold: u32,
    #[serde(default = "default_envs_per_session")]
    pub envs_per_session: u32,
    pub held_seeds: String,
    pub scorer_revision: u32,
}

fn default_envs_per_session() -> u32 {
    DEFAULT_ENVS_PER_SESSION
}

#[derive(Serialize)]
struct TaskFacts<'a> {
    id: &'a str,
    simulator: &'a str,
    max_episode_steps: u32,
    obs_dim: u32,
    act_dim: u32,
    min_episode_reward: f64,
    max_episode_reward: f64,
    min_episode_cost: f64,
    max_episode_cost: f64,
    cost_thresholds: &'a [f64],
}

fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

impl ProtocolParts<'_> {
    pub fn protocol(&self) -> Protocol {
        let facts: Vec<TaskFacts> = self
            .catalog
            .tasks()
            .iter()
            .map(|t| TaskFacts {
                id: t.id.as_str(),
                simulator: &t.simulator_env_id,
                max_episode_steps: t.max_episode_steps,
                obs_dim: t.obs_dim,
                act_dim: t.act_dim,
                min_episode_reward: t.min_episode_reward,
                max_episode_reward: t.max_episode_reward,
                min_episode_cost: t.min_episode_cost,
                max_episode_cost: t.max_episode_cost,
                cost_thresholds: &t.cost_thresholds,
            })
            .collect();
        let catalog_sha256 = sha256_hex(&serde_json::to_vec(&facts).expect("task facts serialize"));
        let simulator_pins_sha256 = sha256_hex(self.simulator_pins.as_bytes());
        let mut parts = serde_json::json!({
            "rules": RULES,
            "catalog": catalog_sha256,
            "simulator_pins": simulator_pins_sha256,
            "episodes_per_threshold": self.episodes_per_threshold,
            "held_seeds": self.held_seeds,
            "scorer_revision": self.scorer_revision,
        });
        if self.envs_per_session != DEFAULT_ENVS_PER_SESSION {
            parts["envs_per_session"] = self.envs_per_session.into();
        }
        let digest = sha256_hex(parts.to_string().as_bytes());
        Protocol {
            version: format!("p{RULES}.{}", &digest[..10]),
            rules: RULES,
            tasks: facts.len(),
            catalog_sha256,
            simulator_pins_sha256,
            episodes_per_threshold: self.episodes_per_threshold,
            envs_per_session: self.envs_per_session,
            held_seeds: self.held_seeds.to_owned(),
            scorer_revision: self.scorer_revision,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_part_changes_the_version() {
        let catalog = Catalog::embedded().unwrap();
        let base = ProtocolParts {
            catalog: &catalog,
            simulator_pins: "safety-gymnasium==1.0.0\n",
            episodes_per_threshold: 20,
            envs_per_session: DEFAULT_ENVS_PER_SESSION,
            held_seeds: "held-seeds/1",
            scorer_revision: 1,
        };
        let version = base.protocol().version;
        assert!(version.starts_with("p1.") && version.len() == 13, "{version}");
        // The default layout is not in the digest's input: the version is the one computed before it was a part.
        // (The committed reference results are checked against the current version by the documents' test.)
        let before = sha256_hex(
            serde_json::json!({
                "rules": RULES,
                "catalog": base.protocol().catalog_sha256,
                "simulator_pins": base.protocol().simulator_pins_sha256,
                "episodes_per_threshold": 20,
                "held_seeds": "held-seeds/1",
                "scorer_revision": 1,
            })
            .to_string()
            .as_bytes(),
        );
        assert_eq!(version, format!("p1.{}", &before[..10]));
        assert_eq!(
            base.protocol().version,
            version,
            "the version is a function of its parts"
        );

        // A task's thresholds, then its normalization constant.
        let mut tasks = catalog.tasks().to_vec();
        tasks[0].cost_thresholds = vec![10.0, 20.0, 30.0];
        let thresholds = Catalog::new(tasks.clone()).unwrap();
        tasks[0] = catalog.tasks()[0].clone();
        tasks[3].max_episode_reward += 1.0;
        let constants = Catalog::new(tasks).unwrap();
        let changed = [
            ProtocolParts {
                catalog: &thresholds,
                ..base.clone()
            },
            ProtocolParts {
                catalog: &constants,
                ..base.clone()
            },
            ProtocolParts {
                simulator_pins: "safety-gymnasium==1.0.1\n",
                ..base.clone()
            },
            ProtocolParts {
                episodes_per_threshold: 10,
                ..base.clone()
            },
            ProtocolParts {
                envs_per_session: 10,
                ..base.clone()
            },
            ProtocolParts {
                held_seeds: "held-seeds/2",
                ..base.clone()
            },
            ProtocolParts {
                scorer_revision: 2,
                ..base.clone()
            },
        ];
        let mut seen = vec![version];
        for parts in changed {
            let v = parts.protocol().version;
            assert!(!seen.contains(&v), "{v} repeats a version");
            seen.push(v);
        }
    }
}
