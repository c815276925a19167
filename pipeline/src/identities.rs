//! Which hostable dataset a version id is: every reference entry names the dataset version it was trained on, and
//! that version must be one some dsrl server can host — a committed starter (`data/starter/versions.csv`, the ids the
//! default server gives the starters, held by the hosted e2e test) or a committed full build (`data/full/<task>.json`).

use std::collections::BTreeMap;
use std::path::Path;

use dsrl_suite::Catalog;

/// The committed starters' version ids: the file, relative to the repository root.
pub const STARTER_VERSIONS: &str = "data/starter/versions.csv";

/// What a version id is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DatasetKind {
    Starter,
    FullBuild,
}

impl DatasetKind {
    pub fn label(self) -> &'static str {
        match self {
            DatasetKind::Starter => "starter",
            DatasetKind::FullBuild => "full build",
        }
    }
}

/// The committed identities: per task, the starter's version and the full build's, where one is committed.
#[derive(Debug, Default)]
pub struct Identities {
    starters: BTreeMap<String, String>,
    full: BTreeMap<String, String>,
}

impl Identities {
    /// Reads `data/starter/versions.csv` (`task,version,trajectories`) and the full builds' records under `root`.
    pub fn read(catalog: &Catalog, root: &Path) -> anyhow::Result<Identities> {
        Identities::with_full_builds(catalog, root, &crate::full::table::read_committed(catalog, root)?)
    }

    /// The same, with the full builds' records already read (`full::table::read_committed`).
    pub fn with_full_builds(
        catalog: &Catalog,
        root: &Path,
        committed: &std::collections::BTreeMap<String, crate::full::table::Committed>,
    ) -> anyhow::Result<Identities> {
        let mut identities = Identities::default();
        let path = root.join(STARTER_VERSIONS);
        let text = std::fs::read_to_string(&path).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        for (i, line) in text.lines().enumerate().skip(1) {
            let fields: Vec<&str> = line.split(',').collect();
            anyhow::ensure!(
                fields.len() == 3 && fields[1].len() == 64,
                "{} line {}: expected task,version,trajectories",
                path.display(),
                i + 1
            );
            catalog.get(fields[0])?;
            identities.starters.insert(fields[0].to_owned(), fields[1].to_owned());
        }
        for (task, build) in committed {
            identities.full.insert(task.clone(), build.record.version.clone());
        }
        Ok(identities)
    }

    /// What `version` is for `task`: its committed starter, its committed full build, or neither (`None`).
    pub fn kind(&self, task: &str, version: &str) -> Option<DatasetKind> {
        if self.starters.get(task).is_some_and(|v| v == version) {
            Some(DatasetKind::Starter)
        } else if self.full.get(task).is_some_and(|v| v == version) {
            Some(DatasetKind::FullBuild)
        } else {
            None
        }
    }

    /// The committed starter versions, by task.
    pub fn starters(&self) -> &BTreeMap<String, String> {
        &self.starters
    }

    /// The committed full build's version of `task`, where one is committed.
    pub fn full_build(&self, task: &str) -> Option<&str> {
        self.full.get(task).map(String::as_str)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every reference entry was trained on a dataset some server can host: its task's committed starter or full
    /// build.
    #[test]
    fn every_reference_entry_names_a_committed_starter_or_full_build() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap();
        let catalog = Catalog::embedded().unwrap();
        let identities = Identities::read(&catalog, root).unwrap();
        assert_eq!(
            identities.starters().len(),
            catalog.tasks().len(),
            "a starter version per task"
        );
        let text = std::fs::read_to_string(root.join("data/reference/results.jsonl")).unwrap();
        let entries = dsrl_scoring::reference::read_results(&text, &catalog).unwrap();
        let unknown: Vec<String> = entries
            .iter()
            .filter(|e| identities.kind(&e.task, &e.dataset_version).is_none())
            .map(|e| format!("{} {} seed {}: {}", e.task, e.method, e.seed, e.dataset_version))
            .collect();
        assert!(
            unknown.is_empty(),
            "trained on no committed dataset:\n{}",
            unknown.join("\n")
        );
    }
}
