//! The task catalog: the 38 DSRL tasks with their simulator ids, horizons, dimensions, normalization constants
//! and benchmark cost thresholds. The data lives in `data/tasks.csv`; it is embedded in the binary as the default
//! and validated whenever it is loaded, so a malformed catalog stops start-up instead of serving wrong scores.

use std::collections::HashMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::ids::TaskId;
use crate::score::{NormalizedScore, normalized_cost, normalized_reward};

/// `data/tasks.csv`, compiled in so the binaries work from any directory.
pub const EMBEDDED_TASKS_CSV: &str = include_str!("../../data/tasks.csv");

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Family {
    #[serde(rename = "bullet")]
    Bullet,
    #[serde(rename = "safetygym-nav")]
    SafetyGymNavigation,
    #[serde(rename = "safetygym-vel")]
    SafetyGymVelocity,
    #[serde(rename = "metadrive")]
    MetaDrive,
}

impl Family {
    pub fn as_str(self) -> &'static str {
        match self {
            Family::Bullet => "bullet",
            Family::SafetyGymNavigation => "safetygym-nav",
            Family::SafetyGymVelocity => "safetygym-vel",
            Family::MetaDrive => "metadrive",
        }
    }

    /// The paper's three benchmark suites, by which the leaderboard and the paper group tasks: `bullet`,
    /// `safety-gymnasium` (navigation and velocity), `metadrive`.
    pub fn suite(self) -> &'static str {
        match self {
            Family::Bullet => "bullet",
            Family::SafetyGymNavigation | Family::SafetyGymVelocity => "safety-gymnasium",
            Family::MetaDrive => "metadrive",
        }
    }
}

/// Which observation space a dataset's observations live in. For MetaDrive the paper's fork produced 261
/// features while the simulator pinned here produces 259; a dataset must match the simulator its policies are
/// scored on, so paper-space data is accepted only when labelled as such.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ObservationSpace {
    #[default]
    Simulator,
    Paper,
}

impl ObservationSpace {
    pub fn as_str(self) -> &'static str {
        match self {
            ObservationSpace::Simulator => "simulator",
            ObservationSpace::Paper => "paper",
        }
    }
}

impl std::str::FromStr for ObservationSpace {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "simulator" => Ok(ObservationSpace::Simulator),
            "paper" => Ok(ObservationSpace::Paper),
            other => Err(format!(
                "unknown observation space {other:?}: expected \"simulator\" or \"paper\""
            )),
        }
    }
}

/// One benchmark task.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Task {
    /// The offline id users type, e.g. `OfflineAntRun-v0`.
    pub id: TaskId,
    pub family: Family,
    /// The simulator's own environment id, e.g. `SafetyAntRun-v0`.
    pub simulator_env_id: String,
    /// Episode horizon (time limit) in steps.
    pub max_episode_steps: u32,
    /// Observation dimension of the paper's datasets.
    pub obs_dim_paper: u32,
    /// Observation dimension the simulator pinned here produces; hosted datasets use this one.
    pub obs_dim: u32,
    pub act_dim: u32,
    /// Normalization constants (DSRL `MIN/MAX_EPISODE_REWARD`, `MIN/MAX_EPISODE_COST`).
    pub min_episode_reward: f64,
    pub max_episode_reward: f64,
    pub min_episode_cost: f64,
    pub max_episode_cost: f64,
    /// The benchmark's cost thresholds for this task, ascending.
    pub cost_thresholds: Vec<f64>,
    /// Number of trajectories in the paper's released file.
    pub paper_trajectories: u32,
    /// Cost-return cap of the paper's released file (the middle number of its file name).
    pub paper_cost_cap: f64,
    /// DSRL's file-name prefix, e.g. `SafetyCarCircle1Gymnasium-v0` (files are `{prefix}-{cap}-{n}.hdf5`).
    pub dataset_file_prefix: String,
}

impl Task {
    pub fn observation_dim(&self, space: ObservationSpace) -> u32 {
        match space {
            ObservationSpace::Simulator => self.obs_dim,
            ObservationSpace::Paper => self.obs_dim_paper,
        }
    }

    /// DSRL's file stem for a dataset of this task with `episodes` trajectories: `{prefix}-{cap}-{n}`.
    pub fn dataset_file_stem(&self, episodes: u64) -> String {
        format!("{}-{}-{}", self.dataset_file_prefix, self.paper_cost_cap, episodes)
    }

    /// The normalized score of an episode (or a mean over episodes) at cost threshold `cost_threshold`.
    pub fn normalized_score(&self, reward_return: f64, cost_return: f64, cost_threshold: f64) -> NormalizedScore {
        NormalizedScore {
            reward: normalized_reward(reward_return, self.min_episode_reward, self.max_episode_reward),
            cost: normalized_cost(cost_return, cost_threshold),
        }
    }

    /// The lowest benchmark threshold: the default target cost where a request names none.
    pub fn lowest_cost_threshold(&self) -> f64 {
        self.cost_thresholds[0]
    }
}

#[derive(Debug, thiserror::Error)]
pub enum CatalogError {
    #[error("cannot read the task catalog {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("task catalog line {line}: {message}")]
    Invalid { line: u64, message: String },
    #[error("task catalog: {0}")]
    Inconsistent(String),
}

/// An id that is not in the catalog, with the nearest ids to suggest.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("unknown task {id:?}{}", suggestion_text(.suggestions))]
pub struct UnknownTask {
    pub id: String,
    pub suggestions: Vec<String>,
}

fn suggestion_text(suggestions: &[String]) -> String {
    if suggestions.is_empty() {
        String::new()
    } else {
        format!("; did you mean {}?", suggestions.join(", "))
    }
}

/// The validated set of tasks, in catalog order.
#[derive(Debug, Clone)]
pub struct Catalog {
    tasks: Vec<Task>,
    by_id: HashMap<String, usize>,
}

/// One CSV row as written in `data/tasks.csv`.
#[derive(Debug, Deserialize)]
struct Row {
    offline_env_id: String,
    family: String,
    simulator_env_id: String,
    max_episode_steps: u32,
    obs_dim: u32,
    act_dim: u32,
    obs_dim_pinned_simulator: u32,
    min_episode_reward: f64,
    max_episode_reward: f64,
    min_episode_cost: f64,
    max_episode_cost: f64,
    cost_thresholds: String,
    paper_trajectories: u32,
    paper_cost_cap: f64,
    dataset_file_prefix: String,
}

impl Catalog {
    /// The catalog compiled from `data/tasks.csv`.
    pub fn embedded() -> Result<Catalog, CatalogError> {
        Catalog::from_csv(EMBEDDED_TASKS_CSV.as_bytes())
    }

    pub fn load(path: &Path) -> Result<Catalog, CatalogError> {
        let bytes = std::fs::read(path).map_err(|source| CatalogError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Catalog::from_csv(&bytes[..])
    }

    pub fn from_csv(reader: impl std::io::Read) -> Result<Catalog, CatalogError> {
        let mut csv = csv::Reader::from_reader(reader);
        let mut tasks = Vec::new();
        for (i, record) in csv.deserialize::<Row>().enumerate() {
            let line = i as u64 + 2; // header is line 1
            let row = record.map_err(|e| CatalogError::Invalid {
                line,
                message: e.to_string(),
            })?;
            let task = task_from_row(row).map_err(|message| CatalogError::Invalid { line, message })?;
            tasks.push(task);
        }
        Catalog::new(tasks)
    }

    pub fn new(tasks: Vec<Task>) -> Result<Catalog, CatalogError> {
        if tasks.is_empty() {
            return Err(CatalogError::Inconsistent("no tasks".into()));
        }
        let mut by_id = HashMap::new();
        for (i, task) in tasks.iter().enumerate() {
            if by_id.insert(task.id.as_str().to_owned(), i).is_some() {
                return Err(CatalogError::Inconsistent(format!("task {} appears twice", task.id)));
            }
        }
        Ok(Catalog { tasks, by_id })
    }

    pub fn tasks(&self) -> &[Task] {
        &self.tasks
    }

    pub fn get(&self, id: &str) -> Result<&Task, UnknownTask> {
        match self.by_id.get(id) {
            Some(&i) => Ok(&self.tasks[i]),
            None => Err(UnknownTask {
                id: id.to_owned(),
                suggestions: self.nearest(id, 3),
            }),
        }
    }

    /// Up to `n` ids nearest to `id`: case-insensitive edit similarity, with a bonus when one contains the other
    /// (so `AntRun` finds `OfflineAntRun-v0`).
    pub fn nearest(&self, id: &str, n: usize) -> Vec<String> {
        let query = id.to_ascii_lowercase();
        let mut scored: Vec<(f64, &str)> = self
            .tasks
            .iter()
            .map(|t| {
                let candidate = t.id.as_str().to_ascii_lowercase();
                let mut score = strsim::normalized_levenshtein(&query, &candidate);
                if !query.is_empty() && candidate.contains(&query) {
                    score += 0.5;
                }
                (score, t.id.as_str())
            })
            .filter(|(score, _)| *score >= 0.5)
            .collect();
        scored.sort_by(|a, b| b.0.total_cmp(&a.0).then_with(|| a.1.cmp(b.1)));
        scored.into_iter().take(n).map(|(_, id)| id.to_owned()).collect()
    }
}

fn task_from_row(row: Row) -> Result<Task, String> {
    let id: TaskId = row.offline_env_id.parse().map_err(|e| format!("{e}"))?;
    let family = match row.family.as_str() {
        "bullet" => Family::Bullet,
        "safetygym-nav" => Family::SafetyGymNavigation,
        "safetygym-vel" => Family::SafetyGymVelocity,
        "metadrive" => Family::MetaDrive,
        other => return Err(format!("unknown family {other:?}")),
    };
    let cost_thresholds = row
        .cost_thresholds
        .split(';')
        .map(|s| {
            s.trim()
                .parse::<f64>()
                .map_err(|e| format!("cost_thresholds {s:?}: {e}"))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let finite = [
        row.min_episode_reward,
        row.max_episode_reward,
        row.min_episode_cost,
        row.max_episode_cost,
        row.paper_cost_cap,
    ];
    if finite.iter().any(|v| !v.is_finite()) {
        return Err(format!("{id}: normalization constants must be finite"));
    }
    if row.min_episode_reward >= row.max_episode_reward {
        return Err(format!("{id}: min_episode_reward must be below max_episode_reward"));
    }
    if row.min_episode_cost > row.max_episode_cost || row.min_episode_cost < 0.0 {
        return Err(format!("{id}: need 0 <= min_episode_cost <= max_episode_cost"));
    }
    if cost_thresholds.is_empty()
        || cost_thresholds.iter().any(|k| !k.is_finite() || *k < 0.0)
        || cost_thresholds.windows(2).any(|w| w[0] >= w[1])
    {
        return Err(format!(
            "{id}: cost_thresholds must be non-negative and strictly ascending"
        ));
    }
    if row.max_episode_steps == 0 || row.obs_dim == 0 || row.act_dim == 0 || row.obs_dim_pinned_simulator == 0 {
        return Err(format!("{id}: horizon and dimensions must be positive"));
    }
    if row.simulator_env_id.is_empty() || row.dataset_file_prefix.is_empty() {
        return Err(format!("{id}: simulator_env_id and dataset_file_prefix must be set"));
    }
    Ok(Task {
        id,
        family,
        simulator_env_id: row.simulator_env_id,
        max_episode_steps: row.max_episode_steps,
        obs_dim_paper: row.obs_dim,
        obs_dim: row.obs_dim_pinned_simulator,
        act_dim: row.act_dim,
        min_episode_reward: row.min_episode_reward,
        max_episode_reward: row.max_episode_reward,
        min_episode_cost: row.min_episode_cost,
        max_episode_cost: row.max_episode_cost,
        cost_thresholds,
        paper_trajectories: row.paper_trajectories,
        paper_cost_cap: row.paper_cost_cap,
        dataset_file_prefix: row.dataset_file_prefix,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_catalog_has_the_38_tasks_by_family() {
        let catalog = Catalog::embedded().unwrap();
        assert_eq!(catalog.tasks().len(), 38);
        let count = |f| catalog.tasks().iter().filter(|t| t.family == f).count();
        assert_eq!(count(Family::Bullet), 8);
        assert_eq!(count(Family::SafetyGymNavigation), 16);
        assert_eq!(count(Family::SafetyGymVelocity), 5);
        assert_eq!(count(Family::MetaDrive), 9);
        for t in catalog.tasks() {
            let expected: &[f64] = match t.family {
                Family::Bullet | Family::MetaDrive => &[10.0, 20.0, 40.0],
                _ => &[20.0, 40.0, 80.0],
            };
            assert_eq!(t.cost_thresholds, expected, "{}", t.id);
        }
    }

    #[test]
    fn embedded_catalog_matches_the_reference_constants() {
        let catalog = Catalog::embedded().unwrap();
        let ant = catalog.get("OfflineAntRun-v0").unwrap();
        assert_eq!(ant.simulator_env_id, "SafetyAntRun-v0");
        assert_eq!((ant.obs_dim, ant.act_dim, ant.max_episode_steps), (33, 8, 200));
        assert_eq!(ant.max_episode_reward, 955.4818725585938);
        assert_eq!(ant.dataset_file_stem(1816), "SafetyAntRun-v0-150-1816");
        let md = catalog.get("OfflineMetadrive-easysparse-v0").unwrap();
        assert_eq!((md.obs_dim_paper, md.obs_dim), (261, 259));
        assert_eq!(md.observation_dim(ObservationSpace::Paper), 261);
        assert_eq!(md.dataset_file_stem(1000), "SafeMetaDrive-easysparse-v0-85-1000");
        let nav = catalog.get("OfflineCarCircle1Gymnasium-v0").unwrap();
        assert_eq!(nav.dataset_file_prefix, "SafetyCarCircle1Gymnasium-v0");
        assert_eq!(nav.simulator_env_id, "SafetyCarCircle1-v0");
    }

    #[test]
    fn unknown_ids_suggest_the_nearest() {
        let catalog = Catalog::embedded().unwrap();
        let err = catalog.get("OfflineAntRun-v1").unwrap_err();
        assert_eq!(err.suggestions[0], "OfflineAntRun-v0");
        let err = catalog.get("AntRun").unwrap_err();
        assert_eq!(err.suggestions[0], "OfflineAntRun-v0");
        assert!(err.to_string().contains("did you mean OfflineAntRun-v0"), "{err}");
        let err = catalog.get("zzzzzzzzzzzzzzzzzzzzzz").unwrap_err();
        assert!(err.suggestions.is_empty());
    }

    #[test]
    fn malformed_catalogs_are_rejected_with_the_line() {
        let header = EMBEDDED_TASKS_CSV.lines().next().unwrap();
        let good = EMBEDDED_TASKS_CSV.lines().nth(1).unwrap();
        let bad_thresholds = good.replace("10;20;40", "40;20");
        let csv = format!("{header}\n{good}\n{bad_thresholds}\n");
        let err = Catalog::from_csv(csv.as_bytes()).unwrap_err();
        assert!(err.to_string().contains("line 3"), "{err}");
        let dup = format!("{header}\n{good}\n{good}\n");
        assert!(
            Catalog::from_csv(dup.as_bytes())
                .unwrap_err()
                .to_string()
                .contains("twice")
        );
        let bad_family = good.replace(",bullet,", ",pong,");
        let err = Catalog::from_csv(format!("{header}\n{bad_family}\n").as_bytes()).unwrap_err();
        assert!(err.to_string().contains("unknown family"), "{err}");
    }
}
