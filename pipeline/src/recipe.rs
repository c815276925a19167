//! Recipes: how one task's dataset is built, as data under `data/recipes/<task>.toml`.

use std::path::{Path, PathBuf};

use dsrl_suite::catalog::{Catalog, Family, Task};
use dsrl_suite::collection::{BufferLimits, FinalGrid};
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Recipe {
    pub task: String,
    /// Root of every random choice: episode seeds, buffer thinning and the final grid filter derive from it.
    pub seed: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub idm_sweep: Option<IdmSweep>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub expert: Option<ExpertSettings>,
    pub buffer: BufferSettings,
    pub final_grid: FinalGridSettings,
}

/// NumPy's `arange(start, stop, step)`: `start + i * step` for `i < ceil((stop - start) / step)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Arange {
    pub start: f64,
    pub stop: f64,
    pub step: f64,
}

impl Arange {
    pub fn values(&self) -> Vec<f64> {
        let n = ((self.stop - self.start) / self.step).ceil().max(0.0) as usize;
        (0..n).map(|i| self.start + i as f64 * self.step).collect()
    }
}

/// MetaDrive (spec 6.5): the noisy IDM driver over a grid of acceleration factors and target speeds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IdmSweep {
    pub acc_factor: Arange,
    pub target_speeds: Vec<f64>,
    pub episodes_per_setting: u32,
    /// How many maps the episodes are drawn from, the task's own first (DSRL's `run_collect.sh` collected on 10;
    /// the task's evaluation environment has its own map only). Left out: 1, which the recipes written before it
    /// mean, so their provenance is unchanged.
    #[serde(default = "one_map", skip_serializing_if = "is_one_map")]
    pub maps: u32,
}

fn one_map() -> u32 {
    1
}

fn is_one_map(maps: &u32) -> bool {
    *maps == 1
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BufferSettings {
    pub max_trajectory: usize,
    pub filter_interval: f64,
    /// Episodes with returns outside these bounds are not stored (FSRL's `rmin`, `rmax`, `cmin`, `cmax`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reward_range: Option<[f64; 2]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cost_range: Option<[f64; 2]>,
}

/// Bullet-Safety-Gym and Safety-Gymnasium (spec 6.1): a Lagrangian policy-gradient expert trained while its cost
/// limit moves from `cost_start` to `cost_end`; every episode it plays is offered to the trajectory buffer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExpertSettings {
    pub algorithm: ExpertAlgorithm,
    pub hidden_sizes: Vec<usize>,
    pub gamma: f64,
    pub gae_lambda: f64,
    pub lr: f64,
    /// PPO's probability-ratio clip.
    pub clip_ratio: f64,
    pub repeat_per_collect: u32,
    pub minibatch_size: usize,
    pub max_grad_norm: f64,
    /// Each collect plays one episode in each of `envs` environments, then updates the policy (FSRL: 10 episodes
    /// per collect). The environments are spread over one session per worker (up to `envs`); how they are grouped
    /// does not change the result, so it does not depend on how many workers run it.
    pub envs: u32,
    /// Environment steps to train for (`--budget-steps` overrides).
    pub budget_steps: u64,
    /// Sessions are reopened and the whole training state saved every this many collects; a killed run resumes
    /// from the last save and gives the same result as an uninterrupted one.
    pub checkpoint_every_collects: u32,
    pub cost_limit: PaperSchedule,
    /// Walk the cost limit from its loose end to its tight end instead of following the paper's schedule
    /// compressed (see [`LooseFirst`]); absent, the paper's schedule.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loose_first: Option<LooseFirst>,
    /// Feed the networks observations normalized by running statistics (see `expert::normalization`); absent,
    /// raw observations as FSRL's experts.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub observation_normalization: bool,
    /// Stop the actor's steps for the rest of an update once a minibatch's approximate KL from the collect's policy
    /// passes 1.5x this (Spinning Up's PPO early stop; the critics keep all their passes). Why: the paper's
    /// TRPO-Lagrangian experts bound each update's KL (target_kl 1e-3), and PPO with many steps per collect
    /// otherwise drifts far from the policy that played (approximate KL past 0.5, sigma collapsing). Absent, no stop.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_kl: Option<f64>,
    /// Weight of the policy's entropy bonus in the actor loss (`loss − coef·H(π)`); with the state-independent
    /// sigma it only pushes log sigma up, against the collapse of exploration. Absent, no bonus (FSRL's experts).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub entropy_coef: Option<f64>,
    /// Start from another build's trained expert instead of random weights (see [`WarmStart`]); absent, a fresh
    /// expert as FSRL's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub warm_start: Option<WarmStart>,
    pub lagrangian: PidGains,
}

/// Warm-starting (issue: reach DSRL's tempting corner cheaply): the expert starts from the networks (actor,
/// critics, observation statistics) of a finished build of `task`'s recipe at `budget_steps`, with fresh optimizers
/// and multiplier, then trains this recipe's schedule. Why: a level-2 navigation task is its level-1 task with more
/// hazards, in the same observation space, and where a budget this machine can run teaches the level-1 expert to
/// push the box but not the level-2 one, the level-1 pusher can start the level-2 expert's loose phase already
/// pushing. The source build's folder is `<state>/../<task>` (its sibling under the same collect folder, as
/// `data/build_datasets.sh` lays them out) unless `dsrl-admin collect --warm-start` names one; the provenance
/// records the source's recipe, steps and the SHA-256 of the weights taken.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WarmStart {
    /// The task whose build's expert this one starts from: same observation and action dimensions.
    pub task: String,
    /// The budget that build trained for (its `--budget-steps`, or its recipe's): a build of another budget is
    /// refused, so the dataset stays reproducible from the two recipes and budgets.
    pub budget_steps: u64,
}

impl ExpertSettings {
    /// The cost limit the expert trains against after `steps` of a `budget`-step run.
    pub fn cost_limit_at(&self, steps: u64, budget: u64) -> f64 {
        match &self.loose_first {
            Some(walk) => walk.limit_at(&self.cost_limit, steps, budget),
            None => self.cost_limit.limit_at(steps, budget),
        }
    }
}

/// A cost-limit walk for small budgets (issue: reach DSRL's tempting corner cheaply). The paper's schedule spends
/// most of a compressed budget at a tight limit before the expert has learned to move, so a budget 30-300x smaller
/// than the paper's never produces trajectories with high reward and high cost. This walk first trains with the
/// schedule's loosest limit (the expert learns the task with lambda near 0: high reward, high cost), then lowers the
/// limit linearly to the schedule's tightest (the constrained expert keeps much of its reward while its cost
/// falls: the frontier), then holds there (the safe end). Every episode of all three phases goes to the buffer.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LooseFirst {
    /// Fraction of the budget trained at the loosest limit.
    pub hold_loose: f64,
    /// Fraction of the budget trained at the tightest limit, at the end.
    pub hold_tight: f64,
    /// The limit held in the loose phase and walked down from, in place of the schedule's loosest; absent, the
    /// schedule's loosest. Why: an expert whose episodes average the buffer's cost cap pays more than the cap on
    /// about half of them, and the buffer drops those, so a task whose loosest limit is its cap keeps few of its
    /// fast episodes (Swimmer's recipe holds 170 of its cap of 200).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loose_limit: Option<f64>,
}

impl LooseFirst {
    pub fn limit_at(&self, schedule: &PaperSchedule, steps: u64, budget: u64) -> f64 {
        let (tight, loosest) = schedule.tightest_and_loosest();
        let loose = self.loose_limit.unwrap_or(loosest);
        let f = steps as f64 / budget.max(1) as f64;
        let descent = 1.0 - self.hold_loose - self.hold_tight;
        if f < self.hold_loose {
            loose
        } else if f >= 1.0 - self.hold_tight || descent <= 0.0 {
            tight
        } else {
            loose - (f - self.hold_loose) / descent * (loose - tight)
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ExpertAlgorithm {
    PpoLagrangian,
}

/// The paper's cost-limit schedule in its epochs (`epochs` of `steps_per_epoch` environment steps); a smaller
/// budget runs the same schedule compressed in proportion.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PaperSchedule {
    pub cost_start: f64,
    pub cost_end: f64,
    pub epoch_start: u32,
    pub epoch_end: u32,
    pub epochs: u32,
    pub steps_per_epoch: u64,
}

impl PaperSchedule {
    /// The schedule's two limits, whichever way it walks them: (tightest, loosest).
    pub fn tightest_and_loosest(&self) -> (f64, f64) {
        (self.cost_start.min(self.cost_end), self.cost_start.max(self.cost_end))
    }

    /// The paper's budget in environment steps.
    pub fn paper_steps(&self) -> u64 {
        u64::from(self.epochs) * self.steps_per_epoch
    }

    /// The cost limit after `steps` of a `budget`-step run: the paper's limit at the same fraction of training.
    pub fn limit_at(&self, steps: u64, budget: u64) -> f64 {
        let epoch = (steps as f64 / budget.max(1) as f64 * f64::from(self.epochs)).floor() as u32;
        crate::expert::lagrangian::CostLimitSchedule {
            cost_start: self.cost_start,
            cost_end: self.cost_end,
            epoch_start: self.epoch_start,
            epoch_end: self.epoch_end,
        }
        .at(epoch)
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PidGains {
    pub kp: f64,
    pub ki: f64,
    pub kd: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FinalGridSettings {
    pub cost_cap: f64,
    pub reward_range: [f64; 2],
    pub cbins: u32,
    pub rbins: u32,
    pub npb: usize,
}

/// One cell of a sweep: the controller settings of `episodes` episodes.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Setting {
    pub index: usize,
    pub acc_factor: f64,
    pub target_speed: f64,
    pub episodes: u32,
    /// The sweep's maps (the same for every setting).
    #[serde(default = "one_map")]
    pub maps: u32,
}

impl Recipe {
    /// `data/recipes/<task>.toml` under the current directory: `dsrl-admin collect` and the data scripts run from
    /// the root of the clone whose recipes they build. (It used to be the source tree the binary was compiled
    /// in, so a binary built in one clone silently built another clone's recipes.)
    pub fn default_path(task: &str) -> PathBuf {
        Path::new("data/recipes").join(format!("{task}.toml"))
    }

    /// The committed recipe in this crate's own source tree, for the unit tests (which run in `pipeline/`).
    #[cfg(test)]
    pub fn committed_path(task: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../data/recipes")
            .join(format!("{task}.toml"))
    }

    pub fn load(path: &Path) -> anyhow::Result<Recipe> {
        let text =
            std::fs::read_to_string(path).map_err(|e| anyhow::anyhow!("reading recipe {}: {e}", path.display()))?;
        toml::from_str(&text).map_err(|e| anyhow::anyhow!("recipe {}: {e}", path.display()))
    }

    /// Checks the recipe against the catalog; returns its task.
    pub fn validate<'c>(&self, catalog: &'c Catalog) -> anyhow::Result<&'c Task> {
        let task = catalog.get(&self.task).map_err(|e| anyhow::anyhow!("recipe: {e}"))?;
        match (&self.idm_sweep, task.family) {
            (Some(sweep), Family::MetaDrive) => {
                anyhow::ensure!(
                    sweep.episodes_per_setting > 0,
                    "idm_sweep.episodes_per_setting must be at least 1"
                );
                anyhow::ensure!(
                    !sweep.acc_factor.values().is_empty(),
                    "idm_sweep.acc_factor is an empty range"
                );
                anyhow::ensure!(!sweep.target_speeds.is_empty(), "idm_sweep.target_speeds is empty");
                anyhow::ensure!(
                    (1..=dsrl_proto::simulator::v1::MAX_IDM_MAPS).contains(&sweep.maps),
                    "idm_sweep.maps must be from 1 to {}, got {}",
                    dsrl_proto::simulator::v1::MAX_IDM_MAPS,
                    sweep.maps
                );
            }
            (Some(_), family) => anyhow::bail!("{}: an IDM sweep needs a MetaDrive task, not {family:?}", task.id),
            (None, _) => match &self.expert {
                Some(expert) => {
                    anyhow::ensure!(
                        task.family != Family::MetaDrive,
                        "{}: MetaDrive datasets come from the IDM sweep, not an expert",
                        task.id
                    );
                    anyhow::ensure!(expert.envs > 0, "expert.envs must be at least 1");
                    anyhow::ensure!(
                        expert.budget_steps > 0 && expert.checkpoint_every_collects > 0,
                        "expert.budget_steps and expert.checkpoint_every_collects must be at least 1"
                    );
                    anyhow::ensure!(
                        !expert.hidden_sizes.is_empty() && !expert.hidden_sizes.contains(&0),
                        "expert.hidden_sizes must be non-empty and positive"
                    );
                    anyhow::ensure!(
                        expert.minibatch_size > 0 && expert.repeat_per_collect > 0,
                        "expert.minibatch_size and expert.repeat_per_collect must be at least 1"
                    );
                    anyhow::ensure!(
                        expert.lr > 0.0 && expert.clip_ratio > 0.0,
                        "expert.lr and clip_ratio must be positive"
                    );
                    anyhow::ensure!(
                        expert.target_kl.is_none_or(|kl| kl > 0.0),
                        "expert.target_kl must be positive (leave it out for no early stop)"
                    );
                    anyhow::ensure!(
                        expert.entropy_coef.is_none_or(|c| c >= 0.0),
                        "expert.entropy_coef must not be negative"
                    );
                    if let Some(warm) = &expert.warm_start {
                        let source = catalog
                            .get(&warm.task)
                            .map_err(|e| anyhow::anyhow!("expert.warm_start.task: {e}"))?;
                        anyhow::ensure!(
                            (source.obs_dim, source.act_dim) == (task.obs_dim, task.act_dim)
                                && source.family != Family::MetaDrive,
                            "expert.warm_start.task {} ({} observation and {} action features) cannot start an \
                             expert of {} ({} and {}): the networks must have the same shapes",
                            warm.task,
                            source.obs_dim,
                            source.act_dim,
                            task.id,
                            task.obs_dim,
                            task.act_dim
                        );
                        anyhow::ensure!(
                            warm.budget_steps > 0,
                            "expert.warm_start.budget_steps must be at least 1"
                        );
                    }
                    anyhow::ensure!(
                        (0.0..=1.0).contains(&expert.gamma) && (0.0..=1.0).contains(&expert.gae_lambda),
                        "expert.gamma and expert.gae_lambda must lie in [0, 1]"
                    );
                    anyhow::ensure!(
                        expert.cost_limit.epochs > 0 && expert.cost_limit.steps_per_epoch > 0,
                        "expert.cost_limit needs epochs and steps_per_epoch"
                    );
                    if let Some(walk) = &expert.loose_first {
                        anyhow::ensure!(
                            (0.0..=1.0).contains(&walk.hold_loose)
                                && (0.0..=1.0).contains(&walk.hold_tight)
                                && walk.hold_loose + walk.hold_tight <= 1.0,
                            "expert.loose_first: hold_loose and hold_tight are fractions of the budget that sum to \
                             at most 1"
                        );
                        if let Some(limit) = walk.loose_limit {
                            let (tight, loosest) = expert.cost_limit.tightest_and_loosest();
                            anyhow::ensure!(
                                (tight..=loosest).contains(&limit),
                                "expert.loose_first.loose_limit {limit} must lie between the schedule's tightest \
                                 ({tight}) and loosest ({loosest}) limits"
                            );
                        }
                    }
                }
                None => anyhow::bail!(
                    "{}: the recipe names no collection method (idm_sweep for MetaDrive, expert otherwise)",
                    task.id
                ),
            },
        }
        anyhow::ensure!(
            self.idm_sweep.is_none() || self.expert.is_none(),
            "a recipe has either idm_sweep or expert, not both"
        );
        anyhow::ensure!(
            self.buffer.max_trajectory > 0,
            "buffer.max_trajectory must be at least 1"
        );
        anyhow::ensure!(
            self.buffer.filter_interval > 1.0,
            "buffer.filter_interval must exceed 1"
        );
        let grid = &self.final_grid;
        anyhow::ensure!(
            grid.cost_cap > 0.0 && grid.cbins > 0 && grid.rbins > 0 && grid.npb > 0,
            "bad final_grid"
        );
        anyhow::ensure!(
            grid.reward_range[0] < grid.reward_range[1],
            "final_grid.reward_range must be increasing"
        );
        Ok(task)
    }

    /// The sweep's settings in order (acceleration outer, speed inner, as DSRL's script loops), with
    /// `episodes_per_setting` optionally scaled down for a smaller budget.
    pub fn settings(&self, episodes_per_setting: Option<u32>) -> Vec<Setting> {
        let Some(sweep) = &self.idm_sweep else {
            return Vec::new();
        };
        let episodes = episodes_per_setting.unwrap_or(sweep.episodes_per_setting);
        let mut out = Vec::new();
        for acc_factor in sweep.acc_factor.values() {
            for &target_speed in &sweep.target_speeds {
                out.push(Setting {
                    index: out.len(),
                    acc_factor,
                    target_speed,
                    episodes,
                    maps: sweep.maps,
                });
            }
        }
        out
    }

    /// The seed of episode `episode` of setting `setting`: distinct across the whole recipe.
    pub fn episode_seed(&self, setting: usize, episode: u32) -> u64 {
        self.seed
            .wrapping_mul(1_000_003)
            .wrapping_add(setting as u64 * 100_000 + u64::from(episode))
    }

    pub fn buffer_limits(&self) -> BufferLimits {
        BufferLimits {
            max_trajectory: self.buffer.max_trajectory,
            filter_interval: self.buffer.filter_interval,
            rmin: self.buffer.reward_range.map_or(f64::NEG_INFINITY, |r| r[0]),
            rmax: self.buffer.reward_range.map_or(f64::INFINITY, |r| r[1]),
            cmin: self.buffer.cost_range.map_or(f64::NEG_INFINITY, |c| c[0]),
            cmax: self.buffer.cost_range.map_or(f64::INFINITY, |c| c[1]),
        }
    }

    pub fn final_grid(&self) -> FinalGrid {
        let g = &self.final_grid;
        FinalGrid {
            cmin: 0.0,
            cmax: g.cost_cap,
            rmin: g.reward_range[0],
            rmax: g.reward_range[1],
            cbins: g.cbins,
            rbins: g.rbins,
            npb: g.npb,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arange_matches_numpy() {
        // np.arange(0, 6.0, 0.6).tolist()
        let want = [
            0.0,
            0.6,
            1.2,
            1.7999999999999998,
            2.4,
            3.0,
            3.5999999999999996,
            4.2,
            4.8,
            5.3999999999999995,
        ];
        assert_eq!(
            Arange {
                start: 0.0,
                stop: 6.0,
                step: 0.6
            }
            .values(),
            want
        );
    }

    #[test]
    fn every_expert_recipe_loads_with_the_papers_settings() {
        let catalog = Catalog::embedded().unwrap();
        let expected: Vec<csv_row::Row> = csv_row::read();
        let experts: Vec<_> = catalog
            .tasks()
            .iter()
            .filter(|t| t.family != Family::MetaDrive)
            .collect();
        assert_eq!(experts.len(), 29);
        for task in experts {
            let recipe = Recipe::load(&Recipe::committed_path(task.id.as_str())).unwrap();
            assert_eq!(recipe.validate(&catalog).unwrap().id, task.id);
            let expert = recipe.expert.as_ref().expect("an expert recipe");
            assert_eq!(recipe.final_grid.cost_cap, task.paper_cost_cap, "{}", task.id);
            assert!(
                recipe.final_grid.reward_range[1] >= task.max_episode_reward,
                "{}",
                task.id
            );
            let row = expected
                .iter()
                .find(|r| task.id.as_str() == format!("Offline{}", &r.task["Safety".len()..]))
                .unwrap_or_else(|| panic!("no expert settings for {}", task.id));
            let (cost_start, cost_end) = SCHEDULE_DEPARTURES
                .iter()
                .find(|(id, ..)| *id == task.id.as_str())
                .map_or((row.cost_start, row.cost_end), |&(_, start, end)| (start, end));
            assert_eq!(
                (
                    expert.cost_limit.cost_start,
                    expert.cost_limit.cost_end,
                    expert.cost_limit.epochs
                ),
                (cost_start, cost_end, row.epochs),
                "{}",
                task.id
            );
            assert_eq!(recipe.buffer.max_trajectory, row.capacity, "{}", task.id);
            assert!(expert.budget_steps <= expert.cost_limit.paper_steps());
        }
    }

    /// Recipes whose cost limits depart from DSRL's on purpose, each said and measured in data/README.md
    /// ("Choices"): the task, and the limits its schedule walks from and to instead.
    const SCHEDULE_DEPARTURES: &[(&str, f64, f64)] = &[("OfflineHopperVelocityGymnasium-v1", 10.0, 200.0)];

    /// DSRL's per-task expert settings, from the reference table the recipes were written from.
    mod csv_row {
        pub struct Row {
            pub task: String,
            pub cost_start: f64,
            pub cost_end: f64,
            pub epochs: u32,
            pub capacity: usize,
        }

        pub fn read() -> Vec<Row> {
            // task,cost_start,cost_end,epoch_start,epoch_end,epoch,max_traj_len,...
            include_str!("../../data/expert_collection.csv")
                .lines()
                .skip(1)
                .map(|line| {
                    let f: Vec<&str> = line.split(',').collect();
                    Row {
                        task: f[0].to_owned(),
                        cost_start: f[1].parse().unwrap(),
                        cost_end: f[2].parse().unwrap(),
                        epochs: f[5].parse().unwrap(),
                        capacity: f[6].parse().unwrap(),
                    }
                })
                .collect()
        }
    }

    #[test]
    fn the_papers_schedule_is_compressed_onto_a_smaller_budget() {
        let schedule = PaperSchedule {
            cost_start: 5.0,
            cost_end: 100.0,
            epoch_start: 100,
            epoch_end: 900,
            epochs: 1000,
            steps_per_epoch: 10_000,
        };
        assert_eq!(schedule.paper_steps(), 10_000_000);
        // A tenth of the budget: paper epoch = steps / 1000.
        assert_eq!(schedule.limit_at(0, 1_000_000), 5.0);
        assert_eq!(schedule.limit_at(100_999, 1_000_000), 5.0);
        assert_eq!(schedule.limit_at(500_000, 1_000_000), 5.0 + 400.0 * 95.0 / 800.0);
        assert_eq!(schedule.limit_at(950_000, 1_000_000), 100.0);
        // The full budget is the paper's schedule itself.
        assert_eq!(
            schedule.limit_at(5_000_000, 10_000_000),
            schedule.limit_at(500_000, 1_000_000)
        );
    }

    #[test]
    fn the_loose_first_walk_holds_descends_and_holds() {
        // SafetyAntRun-v0's limits (5 -> 200 in the paper), walked loose first.
        let schedule = PaperSchedule {
            cost_start: 5.0,
            cost_end: 200.0,
            epoch_start: 400,
            epoch_end: 2500,
            epochs: 2600,
            steps_per_epoch: 10_000,
        };
        let walk = LooseFirst {
            hold_loose: 0.4,
            hold_tight: 0.2,
            loose_limit: None,
        };
        let at = |steps| walk.limit_at(&schedule, steps, 1_000_000);
        assert_eq!(at(0), 200.0);
        assert_eq!(at(399_999), 200.0);
        assert_eq!(at(400_000), 200.0);
        // Halfway through the descent (40% .. 80%): halfway between the limits.
        assert!((at(600_000) - 102.5).abs() < 1e-9);
        assert_eq!(at(800_000), 5.0);
        assert_eq!(at(999_999), 5.0);
        // A descending paper schedule (navigation: 80 -> 5) is walked the same way.
        let nav = PaperSchedule {
            cost_start: 80.0,
            cost_end: 5.0,
            ..schedule
        };
        assert_eq!(walk.limit_at(&nav, 0, 100), 80.0);
        assert_eq!(walk.limit_at(&nav, 90, 100), 5.0);
        // No descent phase: loose, then tight.
        let steps = LooseFirst {
            hold_loose: 0.5,
            hold_tight: 0.5,
            loose_limit: None,
        };
        assert_eq!(steps.limit_at(&nav, 49, 100), 80.0);
        assert_eq!(steps.limit_at(&nav, 50, 100), 5.0);
        // A loose limit inside the schedule's: held, then walked down from.
        let inside = LooseFirst {
            loose_limit: Some(150.0),
            ..walk
        };
        let at = |steps| inside.limit_at(&schedule, steps, 1_000_000);
        assert_eq!(at(0), 150.0);
        assert_eq!(at(399_999), 150.0);
        assert!((at(600_000) - 77.5).abs() < 1e-9);
        assert_eq!(at(800_000), 5.0);
    }

    #[test]
    fn every_metadrive_recipe_loads_and_sweeps_1000_episodes() {
        let catalog = Catalog::embedded().unwrap();
        let metadrive: Vec<_> = catalog
            .tasks()
            .iter()
            .filter(|t| t.family == Family::MetaDrive)
            .collect();
        assert_eq!(metadrive.len(), 9);
        for task in metadrive {
            let recipe = Recipe::load(&Recipe::committed_path(task.id.as_str())).unwrap();
            assert_eq!(recipe.validate(&catalog).unwrap().id, task.id);
            let settings = recipe.settings(None);
            assert_eq!(settings.len(), 50);
            assert_eq!(
                settings.iter().map(|s| s.episodes).sum::<u32>(),
                task.paper_trajectories
            );
            assert_eq!(recipe.final_grid.cost_cap, task.paper_cost_cap);
            // DSRL's 10 collection maps where the hard maps' best returns and the medium maps' cost spread need
            // them; the easy starters were built on their own map (data/README.md, "Choices").
            let maps = if task.id.as_str().contains("-easy") { 1 } else { 10 };
            assert!(settings.iter().all(|s| s.maps == maps), "{}", task.id);
        }
        // A recipe that leaves `maps` out serializes as before (provenance of earlier builds unchanged).
        let easy = Recipe::load(&Recipe::committed_path("OfflineMetadrive-easysparse-v0")).unwrap();
        assert!(!serde_json::to_string(&easy).unwrap().contains("maps"));
        let mut bad = easy.clone();
        bad.idm_sweep.as_mut().unwrap().maps = 0;
        assert!(bad.validate(&catalog).is_err());
    }

    #[test]
    fn a_loose_limit_must_lie_inside_the_schedule_and_is_left_out_when_absent() {
        let catalog = Catalog::embedded().unwrap();
        let recipe = Recipe::load(&Recipe::committed_path("OfflineAntRun-v0")).unwrap();
        // Absent, the recipe serializes as before (provenance of earlier builds unchanged).
        assert!(!serde_json::to_string(&recipe).unwrap().contains("loose_limit"));
        let with_limit = |limit| {
            let mut r = recipe.clone();
            let expert = r.expert.as_mut().unwrap();
            expert.loose_first.as_mut().unwrap().loose_limit = Some(limit);
            r
        };
        // AntRun's schedule runs between 5 and 200.
        assert!(with_limit(150.0).validate(&catalog).is_ok());
        let err = with_limit(250.0).validate(&catalog).unwrap_err().to_string();
        assert!(err.contains("loose_limit 250"), "{err}");
        assert!(with_limit(1.0).validate(&catalog).is_err());
    }

    #[test]
    fn target_kl_and_entropy_coef_are_checked_and_left_out_when_absent() {
        let catalog = Catalog::embedded().unwrap();
        let recipe = Recipe::load(&Recipe::committed_path("OfflineDroneCircle-v0")).unwrap();
        // Absent, the recipe serializes as before (provenance and state identities of earlier builds unchanged).
        let json = serde_json::to_string(&recipe).unwrap();
        assert!(!json.contains("target_kl") && !json.contains("entropy_coef"), "{json}");
        let with = |target_kl, entropy_coef| {
            let mut r = recipe.clone();
            let expert = r.expert.as_mut().unwrap();
            (expert.target_kl, expert.entropy_coef) = (target_kl, entropy_coef);
            r
        };
        assert!(with(Some(0.02), Some(0.01)).validate(&catalog).is_ok());
        for (kl, coef, field) in [
            (Some(0.0), None, "target_kl"),
            (Some(f64::NAN), None, "target_kl"),
            (None, Some(-0.1), "entropy_coef"),
        ] {
            let err = with(kl, coef).validate(&catalog).unwrap_err().to_string();
            assert!(err.contains(field), "{err}");
        }
        // A recipe file names them in [expert].
        let text = std::fs::read_to_string(Recipe::committed_path("OfflineDroneCircle-v0"))
            .unwrap()
            .replace(
                "clip_ratio = 0.2",
                "clip_ratio = 0.2\ntarget_kl = 0.02\nentropy_coef = 0.005",
            );
        let parsed: Recipe = toml::from_str(&text).unwrap();
        let expert = parsed.expert.unwrap();
        assert_eq!((expert.target_kl, expert.entropy_coef), (Some(0.02), Some(0.005)));
    }
}
