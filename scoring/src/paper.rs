//! The paper's results table (DSRL, Liu et al. 2023, its appendix): for each of the 38 tasks and each of OSRL's
//! seven baselines, the normalized reward and cost it reports. These are the numbers researchers cite today, so the
//! leaderboard shows them beside its own entries; they are the paper's self-reported figures (3 training seeds ×
//! 3 cost thresholds × 20 episodes, OSRL's training budgets, DSRL's original datasets and simulator versions), not
//! results this service scored. `data/paper_results.csv` is a verbatim copy of the reference table, embedded here.

use serde::{Deserialize, Serialize};

use dsrl_suite::catalog::Catalog;
use dsrl_suite::score::NormalizedScore;

/// `data/paper_results.csv`, compiled in.
pub const EMBEDDED_PAPER_RESULTS_CSV: &str = include_str!("../../data/paper_results.csv");

/// OSRL's seven baselines, in the paper's column order; these names are also the reference entries' names.
pub const PAPER_METHODS: [&str; 7] = ["BC-All", "BC-Safe", "CDT", "BCQ-Lag", "BEAR-Lag", "CPQ", "COptiDICE"];

/// How the paper's rows were produced, as the leaderboard labels them.
pub const PAPER_LABEL: &str = "the paper's self-reported numbers: 3 training seeds × 3 cost thresholds × 20 \
                               episodes at OSRL's training budgets, on DSRL's original datasets and simulators";

/// One (task, method) cell of the paper's table.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PaperRow {
    pub task: String,
    pub method: String,
    pub normalized_reward: f64,
    pub normalized_cost: f64,
    /// The paper's verdict (normalized cost below 1), as printed.
    pub safe: bool,
}

impl PaperRow {
    pub fn score(&self) -> NormalizedScore {
        NormalizedScore {
            reward: self.normalized_reward,
            cost: self.normalized_cost,
        }
    }
}

/// The paper's table: per-task rows and its family averages (`average:<family>` rows of the CSV).
#[derive(Debug, Clone)]
pub struct PaperResults {
    rows: Vec<PaperRow>,
    family_averages: Vec<PaperRow>,
}

#[derive(Debug, thiserror::Error)]
pub enum PaperError {
    #[error("paper results line {line}: {message}")]
    Invalid { line: u64, message: String },
    #[error("paper results: {0}")]
    Inconsistent(String),
}

#[derive(Deserialize)]
struct Row {
    task: String,
    method: String,
    normalized_reward: f64,
    normalized_cost: f64,
    safe: String,
}

impl PaperResults {
    /// The embedded table, checked against `catalog`: every row's task is in it (or a family average), every method
    /// one of the seven, every number finite, each verdict the paper's rule, no cell twice.
    pub fn embedded(catalog: &Catalog) -> Result<PaperResults, PaperError> {
        PaperResults::from_csv(EMBEDDED_PAPER_RESULTS_CSV.as_bytes(), catalog)
    }

    pub fn from_csv(reader: impl std::io::Read, catalog: &Catalog) -> Result<PaperResults, PaperError> {
        let mut csv = csv::Reader::from_reader(reader);
        let (mut rows, mut family_averages) = (Vec::<PaperRow>::new(), Vec::<PaperRow>::new());
        for (i, record) in csv.deserialize::<Row>().enumerate() {
            let line = i as u64 + 2;
            let invalid = |message: String| PaperError::Invalid { line, message };
            let row = record.map_err(|e| invalid(e.to_string()))?;
            if !PAPER_METHODS.contains(&row.method.as_str()) {
                return Err(invalid(format!("unknown method {:?}", row.method)));
            }
            if !(row.normalized_reward.is_finite() && row.normalized_cost.is_finite()) {
                return Err(invalid("a normalized score is not finite".into()));
            }
            let safe = match row.safe.as_str() {
                "yes" => true,
                "no" => false,
                other => return Err(invalid(format!("safe is {other:?}, not yes or no"))),
            };
            // The paper's verdicts follow the one rule (`score::is_safe`); its table has no cell at exactly 1, where
            // "at most 1" and "below 1" would differ.
            if row.normalized_cost == 1.0 {
                return Err(invalid(
                    "a normalized cost of exactly 1, where the safety rules disagree".into(),
                ));
            }
            if safe != dsrl_suite::score::is_safe(row.normalized_cost) {
                return Err(invalid(format!(
                    "safe = {} disagrees with normalized cost {}",
                    row.safe, row.normalized_cost
                )));
            }
            let parsed = PaperRow {
                task: row.task,
                method: row.method,
                normalized_reward: row.normalized_reward,
                normalized_cost: row.normalized_cost,
                safe,
            };
            let target = if parsed.task.starts_with("average:") {
                &mut family_averages
            } else {
                catalog.get(&parsed.task).map_err(|e| invalid(e.to_string()))?;
                &mut rows
            };
            if target
                .iter()
                .any(|r| r.task == parsed.task && r.method == parsed.method)
            {
                return Err(invalid(format!("{} {} appears twice", parsed.task, parsed.method)));
            }
            target.push(parsed);
        }
        if rows.is_empty() {
            return Err(PaperError::Inconsistent("no rows".into()));
        }
        Ok(PaperResults { rows, family_averages })
    }

    /// Every per-task row, in the file's order.
    pub fn rows(&self) -> &[PaperRow] {
        &self.rows
    }

    /// The paper's rows of one task, in the paper's method order.
    pub fn for_task(&self, task: &str) -> Vec<&PaperRow> {
        PAPER_METHODS.iter().filter_map(|m| self.get(task, m)).collect()
    }

    pub fn get(&self, task: &str, method: &str) -> Option<&PaperRow> {
        self.rows.iter().find(|r| r.task == task && r.method == method)
    }

    /// The paper's own family averages (`bullet`, `safety-gymnasium`, `metadrive`).
    pub fn family_averages(&self) -> &[PaperRow] {
        &self.family_averages
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_table_covers_every_task_with_the_seven_methods() {
        let catalog = Catalog::embedded().unwrap();
        let paper = PaperResults::embedded(&catalog).unwrap();
        for task in catalog.tasks() {
            let methods: Vec<&str> = paper
                .for_task(task.id.as_str())
                .iter()
                .map(|r| r.method.as_str())
                .collect();
            assert_eq!(methods, PAPER_METHODS, "{}", task.id);
        }
        assert_eq!(paper.rows().len(), 38 * 7);
        assert_eq!(paper.family_averages().len(), 3 * 7);
        // One cell, as the paper prints it.
        let row = paper.get("OfflinePointButton1Gymnasium-v0", "BC-Safe").unwrap();
        assert_eq!(
            (row.normalized_reward, row.normalized_cost, row.safe),
            (0.06, 0.52, true)
        );
    }

    #[test]
    fn a_verdict_against_the_rule_or_an_unknown_task_is_refused() {
        let catalog = Catalog::embedded().unwrap();
        let header = "task,method,normalized_reward,normalized_cost,safe\n";
        for (body, expected) in [
            ("OfflineBallRun-v0,CPQ,0.2,1.5,yes\n", "disagrees"),
            ("OfflineBallRunn-v0,CPQ,0.2,0.5,yes\n", "unknown task"),
            ("OfflineBallRun-v0,PPO,0.2,0.5,yes\n", "unknown method"),
            (
                "OfflineBallRun-v0,CPQ,0.2,0.5,yes\nOfflineBallRun-v0,CPQ,0.2,0.5,yes\n",
                "twice",
            ),
        ] {
            let e = PaperResults::from_csv(format!("{header}{body}").as_bytes(), &catalog).unwrap_err();
            assert!(e.to_string().contains(expected), "{e}");
        }
    }
}
