//! The plan of the reference table (`data/reference/plan.toml`): phases, each a list of runs, each run a set of
//! tasks × methods × training seeds at one budget. The plan is data, so the table's budgets are read in one place
//! and a reader sees what was trained without reading the orchestrator.

use std::collections::BTreeMap;
use std::path::Path;

use dsrl_suite::Catalog;
use serde::Deserialize;

/// Where the repository keeps the plan.
pub const PLAN_PATH: &str = "data/reference/plan.toml";

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Plan {
    #[serde(rename = "phase")]
    pub phases: Vec<Phase>,
}

/// One step of the table, run when named: its runs share a scoring server, a state folder and a results file.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Phase {
    pub name: String,
    /// What the phase adds, in a sentence (shown by `--list`).
    pub about: String,
    /// What the models train on: the hosted starters, or each task's full build (hosted by the private scoring
    /// server as the task's `latest`; only tasks with a committed full build take part).
    #[serde(default)]
    pub dataset: Dataset,
    /// The results file its entries go to, from the repository root.
    #[serde(default = "default_results")]
    pub results: String,
    /// Its state folder's name under `~/.dsrl` (models, submissions, the private server's data).
    #[serde(default = "default_state")]
    pub state: String,
    #[serde(rename = "run")]
    pub runs: Vec<Run>,
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Dataset {
    #[default]
    Starter,
    FullBuild,
}

fn default_results() -> String {
    "data/reference/results.jsonl".to_owned()
}

fn default_state() -> String {
    "reference".to_owned()
}

/// Tasks × methods × seeds at one budget. Every model of a run trains in one pool.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Run {
    /// Task ids, or the groups `all`, `bullet`, `safety-gymnasium` and `metadrive` (in the catalog's order).
    pub tasks: Vec<String>,
    /// In the order their models are queued: the longest first lets the pool end on short ones.
    pub methods: Vec<Method>,
    /// Gradient steps per model (OSRL's 100,000 when absent); BEAR-Lag trains three times as many (OSRL's
    /// 300,000 against 100,000) unless `steps_for` names it.
    #[serde(default = "default_steps")]
    pub steps: u64,
    /// Steps of a method, over `steps`.
    #[serde(default)]
    pub steps_for: BTreeMap<Method, u64>,
    /// Instead of each method's own (OSRL's 512, CDT's 2048); recorded with each model.
    pub batch_size: Option<usize>,
    #[serde(default = "default_seeds")]
    pub seeds: Vec<u64>,
}

fn default_steps() -> u64 {
    100_000
}

fn default_seeds() -> Vec<u64> {
    vec![0]
}

/// A method the reference table trains, by its `dsrl-train` command.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    BcAll,
    BcSafe,
    Cdt,
    Bcql,
    Bearl,
    Cpq,
    Coptidice,
    Caps,
    Fisor,
    Lspc,
}

impl Method {
    pub const ALL: [Method; 10] = [
        Method::BcAll,
        Method::BcSafe,
        Method::Cdt,
        Method::Bcql,
        Method::Bearl,
        Method::Cpq,
        Method::Coptidice,
        Method::Caps,
        Method::Fisor,
        Method::Lspc,
    ];

    /// The key in plans, state folders and `dsrl-train`'s output folders.
    pub fn key(self) -> &'static str {
        match self {
            Method::BcAll => "bc-all",
            Method::BcSafe => "bc-safe",
            Method::Cdt => "cdt",
            Method::Bcql => "bcql",
            Method::Bearl => "bearl",
            Method::Cpq => "cpq",
            Method::Coptidice => "coptidice",
            Method::Caps => "caps",
            Method::Fisor => "fisor",
            Method::Lspc => "lspc",
        }
    }

    /// The name in the results file and on the leaderboard.
    pub fn name(self) -> &'static str {
        match self {
            Method::BcAll => "BC-All",
            Method::BcSafe => "BC-Safe",
            Method::Cdt => "CDT",
            Method::Bcql => "BCQ-Lag",
            Method::Bearl => "BEAR-Lag",
            Method::Cpq => "CPQ",
            Method::Coptidice => "COptiDICE",
            Method::Caps => "CAPS",
            Method::Fisor => "FISOR",
            Method::Lspc => "LSPC",
        }
    }

    /// Whether it trains one model per benchmark threshold. BC-All ignores costs; CDT is conditioned on a target
    /// cost, CAPS given each threshold as its budget, FISOR and LSPC never read it: one model each.
    pub fn per_threshold(self) -> bool {
        !matches!(
            self,
            Method::BcAll | Method::Cdt | Method::Caps | Method::Fisor | Method::Lspc
        )
    }

    /// `dsrl-train`'s command and mode for it.
    pub fn train_command(self) -> Vec<&'static str> {
        match self {
            Method::BcAll => vec!["bc", "--mode", "all"],
            Method::BcSafe => vec!["bc", "--mode", "safe"],
            other => vec![other.key()],
        }
    }
}

impl Run {
    /// Steps per model of `method` in this run.
    pub fn steps_of(&self, method: Method) -> u64 {
        match self.steps_for.get(&method) {
            Some(&steps) => steps,
            None if method == Method::Bearl => 3 * self.steps,
            None => self.steps,
        }
    }

    /// The run's task ids, groups expanded in the catalog's order, each once.
    pub fn task_ids(&self, catalog: &Catalog) -> Result<Vec<String>, String> {
        let mut ids: Vec<String> = Vec::new();
        for selector in &self.tasks {
            let chosen: Vec<String> = match selector.as_str() {
                "all" => catalog.tasks().iter().map(|t| t.id.to_string()).collect(),
                "bullet" | "safety-gymnasium" | "metadrive" => catalog
                    .tasks()
                    .iter()
                    .filter(|t| t.family.suite() == selector)
                    .map(|t| t.id.to_string())
                    .collect(),
                id => match catalog.get(id) {
                    Ok(task) => vec![task.id.to_string()],
                    Err(_) => {
                        return Err(format!(
                            "no task or group {id:?} (groups: all, bullet, safety-gymnasium, metadrive; near: {})",
                            catalog.nearest(id, 3).join(", ")
                        ));
                    }
                },
            };
            for id in chosen {
                if !ids.contains(&id) {
                    ids.push(id);
                }
            }
        }
        Ok(ids)
    }
}

impl Plan {
    pub fn load(path: &Path) -> anyhow::Result<Plan> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| anyhow::anyhow!("cannot read the plan {}: {e}", path.display()))?;
        Plan::parse(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
    }

    /// Reads and checks a plan: every phase named once, every run with tasks the catalog knows, methods, seeds
    /// and positive budgets. A typo fails here, before anything trains.
    pub fn parse(text: &str) -> anyhow::Result<Plan> {
        let plan: Plan = toml::from_str(text)?;
        let catalog = Catalog::embedded()?;
        anyhow::ensure!(!plan.phases.is_empty(), "the plan has no [[phase]]");
        for (i, phase) in plan.phases.iter().enumerate() {
            let at = format!("phase {:?}", phase.name);
            anyhow::ensure!(
                !phase.name.is_empty() && !plan.phases[..i].iter().any(|p| p.name == phase.name),
                "{at}: every phase needs a name of its own"
            );
            anyhow::ensure!(
                !phase.state.is_empty() && !phase.state.contains('/') && !phase.state.starts_with('.'),
                "{at}: state {:?} must be a plain folder name (it lives under ~/.dsrl)",
                phase.state
            );
            anyhow::ensure!(!phase.runs.is_empty(), "{at} has no [[phase.run]]");
            for (j, run) in phase.runs.iter().enumerate() {
                let at = format!("{at}, run {}", j + 1);
                anyhow::ensure!(!run.methods.is_empty(), "{at}: name at least one method");
                anyhow::ensure!(!run.seeds.is_empty(), "{at}: name at least one seed");
                anyhow::ensure!(!run.tasks.is_empty(), "{at}: name at least one task or group");
                run.task_ids(&catalog).map_err(|e| anyhow::anyhow!("{at}: {e}"))?;
                anyhow::ensure!(run.steps > 0, "{at}: steps must be positive");
                anyhow::ensure!(run.batch_size != Some(0), "{at}: batch_size must be positive");
                for (method, steps) in &run.steps_for {
                    anyhow::ensure!(*steps > 0, "{at}: steps_for.{} must be positive", method.key());
                }
            }
        }
        Ok(plan)
    }

    /// The named phases in the order asked, or an error naming the plan's phases.
    pub fn phases(&self, names: &[String]) -> anyhow::Result<Vec<&Phase>> {
        names
            .iter()
            .map(|name| {
                self.phases.iter().find(|p| &p.name == name).ok_or_else(|| {
                    let known: Vec<&str> = self.phases.iter().map(|p| p.name.as_str()).collect();
                    anyhow::anyhow!("the plan has no phase {name:?} (its phases: {})", known.join(", "))
                })
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_committed_plan_reads_and_expands_its_groups() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let plan = Plan::load(&root.join(PLAN_PATH)).unwrap();
        let catalog = Catalog::embedded().unwrap();
        let first = &plan.phases[0].runs;
        let tasks: usize = first.iter().map(|r| r.task_ids(&catalog).unwrap().len()).sum();
        assert_eq!(tasks, catalog.tasks().len(), "phase 1 covers every task once");
        assert!(
            plan.phases(&["nope".into()])
                .unwrap_err()
                .to_string()
                .contains("its phases: 1,")
        );
    }

    #[test]
    fn budgets_follow_osrls_ratios_unless_named() {
        let plan = Plan::parse(
            "[[phase]]\nname = \"x\"\nabout = \"\"\n[[phase.run]]\ntasks = [\"OfflineBallRun-v0\"]\n\
             methods = [\"bearl\", \"cpq\", \"bc-all\"]\nsteps = 10\nsteps_for = { cpq = 7 }\n",
        )
        .unwrap();
        let run = &plan.phases[0].runs[0];
        assert_eq!(
            [Method::Bearl, Method::Cpq, Method::BcAll].map(|m| run.steps_of(m)),
            [30, 7, 10]
        );
        assert_eq!(run.seeds, [0]);
    }

    #[test]
    fn mistakes_are_named_before_anything_trains() {
        let base = "[[phase]]\nname = \"x\"\nabout = \"\"\n[[phase.run]]\n";
        for (run, says) in [
            (
                "tasks = [\"OfflineBalRun-v0\"]\nmethods = [\"bc-all\"]",
                "OfflineBallRun-v0",
            ),
            ("tasks = [\"all\"]\nmethods = [\"bc-al\"]", "unknown variant"),
            (
                "tasks = [\"all\"]\nmethods = [\"cpq\"]\nsteps_for = { cpq = 0 }",
                "steps_for.cpq",
            ),
            (
                "tasks = [\"all\"]\nmethods = [\"cpq\"]\nseeds = []",
                "at least one seed",
            ),
            ("tasks = [\"all\"]\nmethods = [\"cpq\"]\nstep = 3", "unknown field"),
        ] {
            let error = Plan::parse(&format!("{base}{run}\n")).unwrap_err().to_string();
            assert!(error.contains(says), "{run}: {error}");
        }
    }
}
