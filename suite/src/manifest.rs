//! The JSON manifest published with every dataset version: what it is (task, spaces, counts), where it came
//! from (provenance), and its episode index. The version id is the sha256 of the Parquet bytes, so a manifest
//! and a file can always be checked against each other.

use serde::{Deserialize, Serialize};

use crate::catalog::{ObservationSpace, Task};
use crate::episode::{EpisodeSummary, return_range};
use crate::ids::{TaskId, VersionId};

/// Format tag of the Parquet layout described in `parquet_file`.
pub const FORMAT: &str = "dsrl-parquet/1";

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format: String,
    pub task: TaskId,
    /// sha256 of the Parquet bytes.
    pub version: VersionId,
    /// DSRL-style file name, `{prefix}-{cap}-{episodes}.parquet`.
    pub file_name: String,
    pub byte_size: u64,
    pub episodes: u64,
    pub transitions: u64,
    pub observation_space: ObservationSpaceInfo,
    pub action_space: ActionSpaceInfo,
    pub reward_return: ValueRange,
    pub cost_return: ValueRange,
    pub provenance: Provenance,
    pub license: String,
    /// RFC 3339 time at which the version was first ingested.
    pub created_at: String,
    /// One entry per episode, in file order.
    pub episode_index: Vec<EpisodeSummary>,
    /// What the version is on the server that serves it (its starter, a full build), added when the manifest is
    /// served: not part of the stored manifest, since a version's tags can change.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hosting: Option<Hosting>,
}

/// What a hosted version is to the server that serves it, from its tags.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Hosting {
    /// `starter` (the committed starter dataset, a cut of a build to fit the repository) or `full` (a full build,
    /// at least the paper's trajectory count where its record says so).
    pub kind: String,
    pub trajectories: u64,
    /// The trajectories of the paper's dataset of the task.
    pub paper_trajectories: u64,
    /// For a starter: one line that says so and names the command that builds the full dataset.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub notice: Option<String>,
}

impl Hosting {
    /// What a version tagged `tags` is, if it is a starter or a full build.
    pub fn of(task: &crate::Task, trajectories: u64, tags: &[String]) -> Option<Hosting> {
        let paper_trajectories = u64::from(task.paper_trajectories);
        if tags.iter().any(|t| t == crate::TagName::FULL) {
            return Some(Hosting {
                kind: crate::TagName::FULL.into(),
                trajectories,
                paper_trajectories,
                notice: None,
            });
        }
        if tags.iter().any(|t| t == crate::TagName::STARTER) {
            return Some(Hosting {
                kind: crate::TagName::STARTER.into(),
                trajectories,
                paper_trajectories,
                notice: Some(starter_notice(task, trajectories)),
            });
        }
        None
    }
}

/// The line a starter is shown with, wherever it is shown.
pub fn starter_notice(task: &crate::Task, trajectories: u64) -> String {
    format!(
        "{} is the starter dataset: {trajectories} of the paper's {} trajectories. The paper-size dataset is built \
         (and uploaded to a server with --server) by `dsrl-admin build {}`; see data/README.md, \"Full builds\".",
        task.id, task.paper_trajectories, task.id
    )
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ObservationSpaceInfo {
    pub kind: ObservationSpace,
    pub dim: u32,
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ActionSpaceInfo {
    pub dim: u32,
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ValueRange {
    pub min: f32,
    pub max: f32,
}

/// Where a version's transitions came from.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Provenance {
    /// Converted from an uploaded file.
    Import {
        /// The file name the uploader gave.
        file_name: String,
        /// sha256 of the uploaded bytes, before conversion.
        sha256: String,
        /// `parquet` or `hdf5`.
        source_format: String,
        /// Source columns/keys that are not part of the format and were not kept.
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        dropped_columns: Vec<String>,
    },
    /// Made from another version by DSRL's post-process filters.
    Filter {
        /// The version filtered.
        parent: String,
        /// The filter in canonical form (only what changes the output, in pipeline order).
        filter: String,
        /// The filter as it was requested.
        request: String,
        /// The seed of the density filter's random sampling, when that filter ran.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        seed: Option<u64>,
        counts: FilterCounts,
        /// What the output reproduces, bit for bit.
        reference: String,
    },
    /// Built by one of our data recipes (see `data/`).
    Recipe {
        recipe: String,
        seeds: Vec<u64>,
        code_version: String,
        /// Budgets and settings the recipe ran with.
        #[serde(default, skip_serializing_if = "serde_json::Value::is_null")]
        #[cfg_attr(feature = "openapi", schema(value_type = Object))]
        details: serde_json::Value,
    },
}

/// One hosted version as the catalog and version listings show it (the manifest without its episode index,
/// plus the tags that point at it now).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HostedVersion {
    pub task: String,
    /// sha256 of the Parquet bytes.
    pub version: String,
    /// Tags that point at this version now, e.g. `latest`.
    pub tags: Vec<String>,
    pub byte_size: u64,
    pub episodes: u64,
    pub transitions: u64,
    /// `simulator` or `paper`.
    pub observation_space: String,
    /// RFC 3339.
    pub created_at: String,
}

/// Everything a manifest needs besides what the conversion measured.
#[derive(Debug, Clone)]
pub struct ManifestFacts {
    pub observation_space: ObservationSpace,
    pub provenance: Provenance,
    pub license: String,
    pub created_at: String,
}

impl Manifest {
    pub fn new(
        task: &Task,
        version: VersionId,
        byte_size: u64,
        episode_index: Vec<EpisodeSummary>,
        facts: ManifestFacts,
    ) -> Manifest {
        let transitions = episode_index.iter().map(|e| e.length as u64).sum();
        let range = |f: fn(&EpisodeSummary) -> f32| {
            let (min, max) = return_range(episode_index.iter().map(f)).unwrap_or((0.0, 0.0));
            ValueRange { min, max }
        };
        let episodes = episode_index.len() as u64;
        Manifest {
            format: FORMAT.to_owned(),
            task: task.id.clone(),
            version,
            file_name: format!("{}.parquet", task.dataset_file_stem(episodes)),
            byte_size,
            episodes,
            transitions,
            observation_space: ObservationSpaceInfo {
                kind: facts.observation_space,
                dim: task.observation_dim(facts.observation_space),
            },
            action_space: ActionSpaceInfo { dim: task.act_dim },
            reward_return: range(|e| e.reward_return),
            cost_return: range(|e| e.cost_return),
            provenance: facts.provenance,
            license: facts.license,
            created_at: facts.created_at,
            episode_index,
            hosting: None,
        }
    }

    /// The DSRL-style HDF5 file name for the same data.
    pub fn hdf5_file_name(&self) -> String {
        let stem = self.file_name.strip_suffix(".parquet").unwrap_or(&self.file_name);
        format!("{stem}.hdf5")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::catalog::Catalog;

    #[test]
    fn counts_ranges_and_names_come_from_the_index() {
        let catalog = Catalog::embedded().unwrap();
        let task = catalog.get("OfflineCarCircle-v0").unwrap();
        let index = vec![
            EpisodeSummary {
                start: 0,
                length: 300,
                reward_return: 12.5,
                cost_return: 3.0,
            },
            EpisodeSummary {
                start: 300,
                length: 120,
                reward_return: -2.0,
                cost_return: 40.0,
            },
        ];
        let version: VersionId = "a".repeat(64).parse().unwrap();
        let m = Manifest::new(
            task,
            version,
            4096,
            index,
            ManifestFacts {
                observation_space: ObservationSpace::Simulator,
                provenance: Provenance::Import {
                    file_name: "x.hdf5".into(),
                    sha256: "b".repeat(64),
                    source_format: "hdf5".into(),
                    dropped_columns: vec![],
                },
                license: "CC-BY-4.0".into(),
                created_at: "2026-11-22T00:00:00Z".into(),
            },
        );
        assert_eq!((m.episodes, m.transitions), (2, 420));
        assert_eq!(m.reward_return, ValueRange { min: -2.0, max: 12.5 });
        assert_eq!(m.cost_return, ValueRange { min: 3.0, max: 40.0 });
        assert_eq!(m.file_name, "SafetyCarCircle-v0-100-2.parquet");
        assert_eq!(m.hdf5_file_name(), "SafetyCarCircle-v0-100-2.hdf5");
        let json = serde_json::to_value(&m).unwrap();
        assert_eq!(json["provenance"]["kind"], "import");
        assert_eq!(json["observation_space"]["kind"], "simulator");
        let back: Manifest = serde_json::from_value(json).unwrap();
        assert_eq!(back, m);
    }
}

/// How many trajectories each step removed or changed.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FilterCounts {
    pub input_episodes: u64,
    pub removed_by_density: u64,
    pub relabelled_outliers: u64,
    pub removed_by_inpaint: u64,
    pub removed_by_epsilon: u64,
    pub output_episodes: u64,
}
