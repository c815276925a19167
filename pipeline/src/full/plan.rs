//! The plan of the full builds (`data/full_builds.toml`): for each task, the keys of its recipe that its full build
//! replaces. A task's full build is its recipe with those keys replaced; the plan's order is the build order.

use std::path::{Path, PathBuf};

use crate::recipe::Recipe;

/// The plan file the repository commits.
pub const PLAN_PATH: &str = "data/full_builds.toml";

/// One task's entry: its overrides, as written.
#[derive(Debug, Clone)]
pub struct PlanEntry {
    pub task: String,
    pub overrides: toml::Table,
}

#[derive(Debug, Clone)]
pub struct Plan {
    /// Where the plan was read from (named in provenance).
    pub path: PathBuf,
    /// In the file's order.
    pub entries: Vec<PlanEntry>,
}

impl Plan {
    pub fn load(path: &Path) -> anyhow::Result<Plan> {
        let text = std::fs::read_to_string(path).map_err(|e| anyhow::anyhow!("reading {}: {e}", path.display()))?;
        let table: toml::Table = toml::from_str(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        let mut entries = Vec::new();
        for (task, value) in table {
            let toml::Value::Table(overrides) = value else {
                anyhow::bail!(
                    "{}: `{task}` must be a table of the recipe keys to replace",
                    path.display()
                );
            };
            entries.push(PlanEntry { task, overrides });
        }
        Ok(Plan {
            path: path.to_owned(),
            entries,
        })
    }

    pub fn entry(&self, task: &str) -> anyhow::Result<&PlanEntry> {
        self.entries
            .iter()
            .find(|e| e.task == task)
            .ok_or_else(|| anyhow::anyhow!("{task} has no entry in {}", self.path.display()))
    }

    /// The tasks to build, in build order: `wanted` in the order given, or every task in the plan's order when
    /// none is, with a warm start's source moved before the task that starts from it (and added if it was not
    /// asked for: its state folder must hold a finished build first).
    pub fn order(&self, wanted: &[String], recipes: &Path) -> anyhow::Result<Vec<String>> {
        for task in wanted {
            self.entry(task)?;
        }
        let mut chosen: Vec<String> = if wanted.is_empty() {
            self.entries.iter().map(|e| e.task.clone()).collect()
        } else {
            let mut unique = Vec::new();
            for task in wanted {
                if !unique.contains(task) {
                    unique.push(task.clone());
                }
            }
            unique
        };
        let mut ordered: Vec<String> = Vec::new();
        while let Some(task) = chosen.first().cloned() {
            chosen.remove(0);
            let mut chain = vec![task];
            // Walk the warm-start chain back to a build that starts from nothing.
            while let Some(source) = self
                .recipe(chain.last().expect("non-empty"), recipes)?
                .expert
                .and_then(|e| e.warm_start)
                .map(|w| w.task)
            {
                anyhow::ensure!(
                    !chain.contains(&source),
                    "the warm starts of {} form a cycle",
                    chain.join(", ")
                );
                chain.push(source);
            }
            for task in chain.into_iter().rev() {
                if !ordered.contains(&task) {
                    chosen.retain(|t| t != &task);
                    ordered.push(task);
                }
            }
        }
        Ok(ordered)
    }

    /// The task's full-build recipe: `recipes/<task>.toml` with the plan's keys replaced, checked field by field
    /// like any recipe (an unknown key is an error).
    pub fn recipe(&self, task: &str, recipes: &Path) -> anyhow::Result<Recipe> {
        let entry = self.entry(task)?;
        let path = recipes.join(format!("{task}.toml"));
        let text = std::fs::read_to_string(&path).map_err(|e| anyhow::anyhow!("reading {}: {e}", path.display()))?;
        let mut table: toml::Table = toml::from_str(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        replace(&mut table, &entry.overrides);
        let recipe: Recipe = toml::Value::Table(table).try_into().map_err(|e| {
            anyhow::anyhow!(
                "{} with {}'s [{task}] keys replaced: {e}",
                path.display(),
                self.path.display()
            )
        })?;
        anyhow::ensure!(
            recipe.task == task,
            "{} is the recipe of {}, not {task}",
            path.display(),
            recipe.task
        );
        Ok(recipe)
    }

    /// How provenance names a full build's recipe.
    pub fn recipe_name(&self, task: &str) -> String {
        format!("data/recipes/{task}.toml with [{task}] of {}", self.path.display())
    }
}

/// Replaces in `base` every key `overrides` names, descending into tables (`expert.budget_steps` replaces one key
/// of `[expert]`, not the whole table).
fn replace(base: &mut toml::Table, overrides: &toml::Table) {
    for (key, value) in overrides {
        match (base.get_mut(key), value) {
            (Some(toml::Value::Table(inner)), toml::Value::Table(over)) => replace(inner, over),
            _ => {
                base.insert(key.clone(), value.clone());
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn recipes() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/recipes")
    }

    fn committed() -> Plan {
        Plan::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../").join(PLAN_PATH)).unwrap()
    }

    #[test]
    fn every_task_has_a_full_build_whose_recipe_parses_and_reaches_for_the_papers_count() {
        let catalog = dsrl_suite::Catalog::embedded().unwrap();
        let plan = committed();
        let planned: Vec<&str> = plan.entries.iter().map(|e| e.task.as_str()).collect();
        let mut all: Vec<&str> = catalog.tasks().iter().map(|t| t.id.as_str()).collect();
        let mut sorted = planned.clone();
        sorted.sort_unstable();
        all.sort_unstable();
        assert_eq!(sorted, all, "the plan names each of the 38 tasks once");
        for entry in &plan.entries {
            let recipe = plan.recipe(&entry.task, &recipes()).unwrap();
            let task = recipe.validate(&catalog).unwrap();
            let paper = task.paper_trajectories as usize;
            match (&recipe.expert, &recipe.idm_sweep) {
                (Some(expert), None) => {
                    // The buffer keeps at least its capacity once it has seen enough: the capacity is the count.
                    assert!(
                        recipe.buffer.max_trajectory >= paper,
                        "{}: capacity under the paper's",
                        task.id
                    );
                    // Whole episodes at the horizon give the fewest; episodes that end early give more.
                    let fewest = expert.budget_steps / u64::from(task.max_episode_steps);
                    assert!(
                        fewest as usize >= paper || task.max_episode_steps < 1000,
                        "{}: 1000-step episodes cannot reach the count",
                        task.id
                    );
                }
                (None, Some(sweep)) => {
                    let settings = recipe.settings(None).len();
                    assert_eq!(settings * sweep.episodes_per_setting as usize, 1000, "{}", task.id);
                    assert_eq!(sweep.maps, 10, "{}: DSRL's 10 collection maps", task.id);
                }
                _ => unreachable!("a recipe is an expert or a sweep"),
            }
        }
    }

    #[test]
    fn overrides_replace_single_keys_and_a_typo_is_refused() {
        let plan = committed();
        let recipe = plan.recipe("OfflinePointPush2Gymnasium-v0", &recipes()).unwrap();
        let committed = Recipe::load(&recipes().join("OfflinePointPush2Gymnasium-v0.toml")).unwrap();
        let (full, base) = (recipe.expert.unwrap(), committed.expert.unwrap());
        assert_eq!(full.budget_steps, 4_200_000);
        assert_eq!(full.warm_start.as_ref().unwrap().budget_steps, 4_100_000);
        assert_eq!(full.warm_start.unwrap().task, base.warm_start.unwrap().task);
        assert_eq!(full.lr, base.lr, "keys the plan does not name are the recipe's");
        assert_eq!(recipe.buffer.max_trajectory, 3300);

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("plan.toml");
        std::fs::write(&path, "[OfflineBallRun-v0]\nexpert.budget_step = 5\n").unwrap();
        let err = Plan::load(&path)
            .unwrap()
            .recipe("OfflineBallRun-v0", &recipes())
            .unwrap_err()
            .to_string();
        assert!(err.contains("budget_step"), "{err}");
    }

    #[test]
    fn a_warm_start_source_is_built_first() {
        let plan = committed();
        let order = plan
            .order(&["OfflinePointPush2Gymnasium-v0".into()], &recipes())
            .unwrap();
        assert_eq!(
            order,
            ["OfflinePointPush1Gymnasium-v0", "OfflinePointPush2Gymnasium-v0"]
        );
        let named = plan
            .order(
                &[
                    "OfflineCarRun-v0".into(),
                    "OfflineBallRun-v0".into(),
                    "OfflineCarRun-v0".into(),
                ],
                &recipes(),
            )
            .unwrap();
        assert_eq!(
            named,
            ["OfflineCarRun-v0", "OfflineBallRun-v0"],
            "named tasks keep the order given"
        );
        let all = plan.order(&[], &recipes()).unwrap();
        assert_eq!(all.len(), 38);
        let at = |t: &str| all.iter().position(|x| x == t).unwrap();
        assert!(at("OfflinePointPush1Gymnasium-v0") < at("OfflinePointPush2Gymnasium-v0"));
        assert_eq!(all[0], "OfflineCarPush2Gymnasium-v0");
        assert!(plan.order(&["OfflineNope-v0".into()], &recipes()).is_err());
    }
}
