//! Rows that methods beyond the paper publish for DSRL's tasks (FISOR's Table 1), shown on the leaderboard beside
//! the paper's rows and our reference entries of the same method. Like the paper's they are self-reported, but under
//! each source's own protocol (FISOR: one cost limit of 10, unseeded resets), which `data/published_sources.csv`
//! states beside the citation; they never enter the agreement with the paper. Both files are embedded.

use serde::{Deserialize, Serialize};

use dsrl_suite::catalog::Catalog;

pub const EMBEDDED_PUBLISHED_RESULTS_CSV: &str = include_str!("../../data/published_results.csv");
pub const EMBEDDED_PUBLISHED_SOURCES_CSV: &str = include_str!("../../data/published_sources.csv");

/// Methods whose published rows are shown: those of the reference methods beyond the paper that publish DSRL scores.
pub const PUBLISHED_METHODS: [&str; 2] = ["FISOR", "LSPC"];

/// One (task, method) row as its source prints it.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PublishedRow {
    pub task: String,
    pub method: String,
    pub normalized_reward: f64,
    pub normalized_cost: f64,
    /// Normalized cost below 1, the paper's rule, applied to the printed cost.
    pub safe: bool,
    /// Where the numbers are printed.
    pub citation: String,
    /// How the source produced them (seeds, episodes, cost limit), in its own words.
    pub protocol: String,
}

#[derive(Debug, thiserror::Error)]
pub enum PublishedError {
    #[error("{file} line {line}: {message}")]
    Invalid {
        file: &'static str,
        line: u64,
        message: String,
    },
}

#[derive(Deserialize)]
struct Row {
    method: String,
    task: String,
    normalized_reward: f64,
    normalized_cost: f64,
    source: String,
}

#[derive(Deserialize)]
struct Source {
    source: String,
    citation: String,
    protocol: String,
}

#[derive(Debug, Clone)]
pub struct PublishedResults {
    rows: Vec<PublishedRow>,
}

impl PublishedResults {
    /// The embedded rows, checked against `catalog`: known tasks and methods, finite numbers, a named source, no
    /// row twice.
    pub fn embedded(catalog: &Catalog) -> Result<PublishedResults, PublishedError> {
        PublishedResults::from_csv(
            EMBEDDED_PUBLISHED_RESULTS_CSV.as_bytes(),
            EMBEDDED_PUBLISHED_SOURCES_CSV.as_bytes(),
            catalog,
        )
    }

    pub fn from_csv(
        rows: impl std::io::Read,
        sources: impl std::io::Read,
        catalog: &Catalog,
    ) -> Result<PublishedResults, PublishedError> {
        let mut known = Vec::new();
        for (i, source) in csv::Reader::from_reader(sources).deserialize::<Source>().enumerate() {
            let source = source.map_err(|e| PublishedError::Invalid {
                file: "data/published_sources.csv",
                line: i as u64 + 2,
                message: e.to_string(),
            })?;
            known.push(source);
        }
        let mut out: Vec<PublishedRow> = Vec::new();
        for (i, row) in csv::Reader::from_reader(rows).deserialize::<Row>().enumerate() {
            let invalid = |message: String| PublishedError::Invalid {
                file: "data/published_results.csv",
                line: i as u64 + 2,
                message,
            };
            let row = row.map_err(|e| invalid(e.to_string()))?;
            catalog.get(&row.task).map_err(|e| invalid(e.to_string()))?;
            if !PUBLISHED_METHODS.contains(&row.method.as_str()) {
                return Err(invalid(format!("unknown method {:?}", row.method)));
            }
            if !(row.normalized_reward.is_finite() && row.normalized_cost.is_finite()) {
                return Err(invalid("a normalized score is not finite".into()));
            }
            let source = known
                .iter()
                .find(|s| s.source == row.source)
                .ok_or_else(|| invalid(format!("source {:?} is not in data/published_sources.csv", row.source)))?;
            if out.iter().any(|r| r.task == row.task && r.method == row.method) {
                return Err(invalid(format!("{} {} appears twice", row.task, row.method)));
            }
            out.push(PublishedRow {
                safe: dsrl_suite::score::is_safe(row.normalized_cost),
                task: row.task,
                method: row.method,
                normalized_reward: row.normalized_reward,
                normalized_cost: row.normalized_cost,
                citation: source.citation.clone(),
                protocol: source.protocol.clone(),
            });
        }
        Ok(PublishedResults { rows: out })
    }

    pub fn rows(&self) -> &[PublishedRow] {
        &self.rows
    }

    /// The rows of one task, in [`PUBLISHED_METHODS`] order.
    pub fn for_task(&self, task: &str) -> Vec<&PublishedRow> {
        PUBLISHED_METHODS
            .iter()
            .filter_map(|m| self.rows.iter().find(|r| r.task == task && r.method == *m))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_rows_are_fisors_table_on_its_26_tasks() {
        let catalog = Catalog::embedded().unwrap();
        let published = PublishedResults::embedded(&catalog).unwrap();
        assert_eq!(published.rows().len(), 26);
        let ball_run = published.for_task("OfflineBallRun-v0");
        assert_eq!(ball_run.len(), 1);
        assert_eq!(
            (ball_run[0].normalized_reward, ball_run[0].normalized_cost),
            (0.18, 0.0)
        );
        assert!(ball_run[0].safe && ball_run[0].citation.contains("ICLR 2024"));
        assert!(ball_run[0].protocol.contains("cost limit 10"));
        // FISOR does not report the Point tasks.
        assert!(published.for_task("OfflinePointGoal1Gymnasium-v0").is_empty());
    }

    #[test]
    fn unknown_tasks_methods_and_sources_are_refused_with_the_line() {
        let catalog = Catalog::embedded().unwrap();
        let sources = "source,citation,protocol\ns,c,p\n";
        let header = "method,task,normalized_reward,normalized_cost,source\n";
        let refused = |row: &str| {
            PublishedResults::from_csv(format!("{header}{row}\n").as_bytes(), sources.as_bytes(), &catalog)
                .err()
                .unwrap()
                .to_string()
        };
        assert!(refused("FISOR,OfflineNoSuch-v0,0.1,0.2,s").contains("line 2"));
        assert!(refused("BC-All,OfflineBallRun-v0,0.1,0.2,s").contains("unknown method"));
        assert!(refused("FISOR,OfflineBallRun-v0,0.1,0.2,t").contains("source \"t\""));
        let twice = "FISOR,OfflineBallRun-v0,0.1,0.2,s\nFISOR,OfflineBallRun-v0,0.1,0.2,s";
        assert!(refused(twice).contains("appears twice"));
    }
}
