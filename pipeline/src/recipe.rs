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
    pub idm_sweep: Option<IdmSweep>,
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
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BufferSettings {
    pub max_trajectory: usize,
    pub filter_interval: f64,
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
}

impl Recipe {
    pub fn default_path(task: &str) -> PathBuf {
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
            }
            (Some(_), family) => anyhow::bail!("{}: an IDM sweep needs a MetaDrive task, not {family:?}", task.id),
            (None, _) => anyhow::bail!(
                "{}: the recipe names no collection method (this build knows idm_sweep, for MetaDrive; expert \
                 training recipes for Bullet and Safety-Gymnasium are not implemented yet)",
                task.id
            ),
        }
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
            rmin: f64::NEG_INFINITY,
            rmax: f64::INFINITY,
            cmin: f64::NEG_INFINITY,
            cmax: f64::INFINITY,
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
    fn every_metadrive_recipe_loads_and_sweeps_1000_episodes() {
        let catalog = Catalog::embedded().unwrap();
        let metadrive: Vec<_> = catalog
            .tasks()
            .iter()
            .filter(|t| t.family == Family::MetaDrive)
            .collect();
        assert_eq!(metadrive.len(), 9);
        for task in metadrive {
            let recipe = Recipe::load(&Recipe::default_path(task.id.as_str())).unwrap();
            assert_eq!(recipe.validate(&catalog).unwrap().id, task.id);
            let settings = recipe.settings(None);
            assert_eq!(settings.len(), 50);
            assert_eq!(
                settings.iter().map(|s| s.episodes).sum::<u32>(),
                task.paper_trajectories
            );
            assert_eq!(recipe.final_grid.cost_cap, task.paper_cost_cap);
        }
    }
}
