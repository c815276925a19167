//! The filter decisions, computed from the episode index alone (returns and lengths; no observations): which
//! trajectories remain and in which order, which are relabelled as outliers, and the random generator state the
//! observation noise continues from. Each step follows DSRL's `pre_process_data` (with the current reference's
//! bounds, spec §3.9), including NumPy 1.24's dtypes: returns are float32; a float32 array compared with a Python
//! or NumPy float compares in float32 after rounding the threshold; scalar-with-scalar arithmetic and comparisons
//! promote to float64.

use std::collections::HashMap;

use crate::spec::{FilterError, FilterSpec, Grid, InpaintRange};
use dsrl_pynumerics::nprandom::NumpyGenerator;
use dsrl_pynumerics::numpy_math::floor_divide;
use dsrl_pynumerics::pyrandom::PyRandom;
use dsrl_suite::catalog::Task;
use dsrl_suite::episode::EpisodeSummary;

/// Seed of the NumPy generator DSRL's `OfflineEnv` creates (`Generator(PCG64(seed=1234))`).
pub const DSRL_GENERATOR_SEED: u64 = 1234;

pub use dsrl_suite::episode::Fate;
pub use dsrl_suite::manifest::FilterCounts;

#[derive(Debug, Clone)]
pub struct Plan {
    /// Input episode indices in output order.
    pub order: Vec<usize>,
    /// Outliers: input episode → the steps whose cost becomes 1 (every other step's cost becomes 0; rewards ×1.5).
    pub relabels: HashMap<usize, Vec<usize>>,
    /// Per input episode, what happened to it.
    pub fates: Vec<Fate>,
    /// Per input episode, the (cost, reward) returns DSRL's decisions saw after relabelling.
    pub returns: Vec<(f32, f32)>,
    pub counts: FilterCounts,
    /// The observation-noise scale, and the generator positioned where DSRL's noise draws start.
    pub noise_scale: Option<f64>,
    pub generator: NumpyGenerator,
}

fn reject(message: impl Into<String>) -> FilterError {
    FilterError::data(message)
}

/// A float32 array element compared with a float scalar, as NumPy 1.x does it: the scalar is rounded to float32
/// when it fits (value-based casting), otherwise the comparison happens in float64.
#[derive(Clone, Copy)]
struct Threshold(f64);

impl Threshold {
    fn le(self, v: f32) -> bool {
        if self.0.abs() <= f32::MAX as f64 {
            (self.0 as f32) <= v
        } else {
            self.0 <= v as f64
        }
    }
    fn ge(self, v: f32) -> bool {
        if self.0.abs() <= f32::MAX as f64 {
            (self.0 as f32) >= v
        } else {
            self.0 >= v as f64
        }
    }
    fn lt(self, v: f32) -> bool {
        !self.ge(v)
    }
}

/// A bound of the grid filter, which is either a float32 data extreme or a Python float from the catalog.
#[derive(Clone, Copy)]
enum Bound {
    F32(f32),
    F64(f64),
}

impl Bound {
    fn value(self) -> f64 {
        match self {
            Bound::F32(v) => v as f64,
            Bound::F64(v) => v,
        }
    }
    /// `x - bound` with NumPy's scalar promotion.
    fn offset(self, x: f32) -> f64 {
        match self {
            Bound::F32(b) => (x - b) as f64,
            Bound::F64(b) => x as f64 - b,
        }
    }
}

/// `(hi - lo) / bins` with NumPy's scalar promotion (a float32 difference divided by a Python int is float64).
fn bin_step(lo: Bound, hi: Bound, bins: u32) -> f64 {
    match (lo, hi) {
        (Bound::F32(a), Bound::F32(b)) => (b - a) as f64 / bins as f64,
        _ => (hi.value() - lo.value()) / bins as f64,
    }
}

/// `max(min(values), floor)` and `min(max(values), ceiling)` with Python's builtins: the catalog constant wins
/// only if it is strictly beyond the data extreme.
fn clip_bounds(values: &[f32], floor: f64, ceiling: f64) -> (Bound, Bound) {
    let data_min = values.iter().copied().fold(f32::INFINITY, f32::min);
    let data_max = values.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let lo = if floor > data_min as f64 {
        Bound::F64(floor)
    } else {
        Bound::F32(data_min)
    };
    let hi = if ceiling < data_max as f64 {
        Bound::F64(ceiling)
    } else {
        Bound::F32(data_max)
    };
    (lo, hi)
}

/// DSRL's `grid_filter` over (cost, reward) returns; returns the kept positions in DSRL's order.
fn grid_filter(
    cost: &[f32],
    reward: &[f32],
    task: &Task,
    grid: &Grid,
    random: &mut PyRandom,
) -> Result<Vec<usize>, FilterError> {
    let (xmin, xmax) = clip_bounds(cost, task.min_episode_cost, task.max_episode_cost);
    let (ymin, ymax) = clip_bounds(reward, task.min_episode_reward, task.max_episode_reward);
    let xstep = bin_step(xmin, xmax, grid.cbins);
    let ystep = bin_step(ymin, ymax, grid.rbins);
    // Also catches NaN steps.
    if xstep.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)
        || ystep.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)
    {
        return Err(reject(format!(
            "the density grid has zero width: the cost returns span [{}, {}] and the reward returns [{}, {}] \
             after clipping to the task's range, so DSRL would divide by zero",
            xmin.value(),
            xmax.value(),
            ymin.value(),
            ymax.value()
        )));
    }
    // Bins in order of first appearance (a Python dict), keyed by the float bin indices.
    let mut bins: Vec<Vec<usize>> = Vec::new();
    let mut slot: HashMap<(u64, u64), usize> = HashMap::new();
    let key = |v: f64| if v == 0.0 { 0u64 } else { v.to_bits() };
    for i in 0..cost.len() {
        let (x, y) = (cost[i] as f64, reward[i] as f64);
        if x < xmin.value() || x > xmax.value() || y < ymin.value() || y > ymax.value() {
            continue;
        }
        let bx = floor_divide(xmin.offset(cost[i]), xstep);
        let by = floor_divide(ymin.offset(reward[i]), ystep);
        let k = (key(bx), key(by));
        let n = bins.len();
        let s = *slot.entry(k).or_insert(n);
        if s == n {
            bins.push(Vec::new());
        }
        bins[s].push(i);
    }
    let mut kept = Vec::new();
    for members in bins {
        if members.len() > grid.max_npb as usize {
            kept.extend(random.sample(&members, grid.max_npb as usize));
        } else if members.len() <= grid.min_npb as usize {
            continue;
        } else {
            kept.extend(members);
        }
    }
    Ok(kept)
}

/// Whether a trajectory lies in DSRL's tempting corner, where the noise filter draws its outliers: cost return at
/// least half the task's `max_episode_cost` and reward return at least half its `max_episode_reward`, compared as
/// NumPy compares float32 returns with a float threshold.
pub fn in_tempting_corner(task: &Task, cost_return: f32, reward_return: f32) -> bool {
    Threshold(task.max_episode_cost / 2.0).le(cost_return) && Threshold(task.max_episode_reward / 2.0).le(reward_return)
}

/// Computes the whole plan.
pub fn plan(spec: &FilterSpec, task: &Task, episodes: &[EpisodeSummary]) -> Result<Plan, FilterError> {
    let mut counts = FilterCounts {
        input_episodes: episodes.len() as u64,
        ..Default::default()
    };
    let mut fates = vec![Fate::Kept; episodes.len()];
    let mut returns: Vec<(f32, f32)> = episodes.iter().map(|e| (e.cost_return, e.reward_return)).collect();
    // Position in DSRL's `trajs` list -> input episode index.
    let mut current: Vec<usize> = (0..episodes.len()).collect();

    if let Some(grid) = &spec.grid {
        let cost: Vec<f32> = episodes.iter().map(|e| e.cost_return).collect();
        let reward: Vec<f32> = episodes.iter().map(|e| e.reward_return).collect();
        let mut random = PyRandom::seed(spec.seed);
        current = grid_filter(&cost, &reward, task, grid, &mut random)?;
        let mut kept = vec![false; episodes.len()];
        for &e in &current {
            kept[e] = true;
        }
        for (e, k) in kept.iter().enumerate() {
            if !k {
                fates[e] = Fate::RemovedByDensity;
            }
        }
        counts.removed_by_density = (episodes.len() - current.len()) as u64;
    }
    let n = current.len();
    let mut cost: Vec<f32> = current.iter().map(|&e| episodes[e].cost_return).collect();
    let mut reward: Vec<f32> = current.iter().map(|&e| episodes[e].reward_return).collect();
    let mut generator = NumpyGenerator::new(DSRL_GENERATOR_SEED);
    let mut relabels = HashMap::new();
    let mut outlier_positions = Vec::new();

    if let Some(percent) = spec.outliers_percent {
        let wanted = ((n as f64 * percent) as usize).max(1);
        let candidates: Vec<usize> = (0..n)
            .filter(|&p| in_tempting_corner(task, cost[p], reward[p]))
            .collect();
        if candidates.len() < wanted {
            return Err(reject(format!(
                "outliers_percent={percent} needs {wanted} trajectories with cost return >= {} and reward return \
                 >= {}, but only {} qualify",
                task.max_episode_cost / 2.0,
                task.max_episode_reward / 2.0,
                candidates.len()
            )));
        }
        let picks = generator.choice_without_replacement(candidates.len(), wanted);
        outlier_positions = picks.iter().map(|&i| candidates[i]).collect();
        // DSRL's `int(target_cost)`; the spec bounds target_cost to [1, MAX_TARGET_COST] for outliers, checked
        // again here because a saturating cast would hand the generator an empty or absurd range.
        let cost_population = spec.target_cost.trunc();
        if !(1.0..=crate::spec::MAX_TARGET_COST).contains(&cost_population) {
            return Err(reject(format!(
                "outliers need 1 <= target_cost <= {}, got {}",
                crate::spec::MAX_TARGET_COST,
                spec.target_cost
            )));
        }
        let cost_values = generator.choice_with_replacement(cost_population as usize, wanted);
        for (&p, &c) in outlier_positions.iter().zip(&cost_values) {
            let length = episodes[current[p]].length as usize;
            if c > length {
                return Err(reject(format!(
                    "an outlier drawn for an episode of {length} steps got cost return {c}: more unit costs than \
                     steps (DSRL fails here too); lower target_cost or use a dataset of longer episodes"
                )));
            }
            let steps = generator.choice_without_replacement(length, c);
            relabels.insert(current[p], steps);
            cost[p] = c as f32;
            reward[p] = (1.5 * reward[p] as f64) as f32;
            fates[current[p]] = Fate::Relabelled;
            returns[current[p]] = (cost[p], reward[p]);
        }
        counts.relabelled_outliers = wanted as u64;
    }

    let mut order: Vec<usize> = (0..n).collect(); // DSRL's traj_idx
    if let Some(r) = &spec.inpaint {
        order = inpaint(r, task, &cost, &reward, &order)?;
        let remaining: std::collections::HashSet<usize> = order.iter().copied().collect();
        for p in &outlier_positions {
            if !remaining.contains(p) {
                order.push(*p);
            }
        }
        for p in 0..n {
            if !order.contains(&p) {
                fates[current[p]] = Fate::RemovedByInpaint;
            }
        }
        counts.removed_by_inpaint = (n - order.len()) as u64;
    }
    if let Some(eps) = spec.epsilon {
        let target = Threshold(spec.target_cost);
        // Positions of the full list; `order` is still 0..n here (inpaint cannot be combined with epsilon).
        let group: Vec<usize> = if eps > 0.0 {
            (0..n).filter(|&p| target.ge(cost[p])).collect()
        } else {
            (0..n).filter(|&p| target.lt(cost[p])).collect()
        };
        if group.is_empty() {
            return Err(reject(format!(
                "epsilon={eps} works on the {} trajectories (cost return {} target_cost={}), and there are none",
                if eps > 0.0 { "safe" } else { "unsafe" },
                if eps > 0.0 { "<=" } else { ">" },
                spec.target_cost
            )));
        }
        let best = group.iter().map(|&p| reward[p]).fold(f32::NEG_INFINITY, f32::max);
        // `ret - epsilon` is a float32 scalar minus a Python float: float64.
        let floor = Threshold(best as f64 - eps.abs());
        let removed: Vec<usize> = group
            .into_iter()
            .filter(|&p| floor.le(reward[p]) && reward[p] <= best)
            .collect();
        for &p in &removed {
            fates[current[p]] = Fate::RemovedByEpsilon;
        }
        // np.setdiff1d sorts.
        order.retain(|p| !removed.contains(p));
        order.sort_unstable();
        counts.removed_by_epsilon = removed.len() as u64;
    }
    if order.is_empty() {
        return Err(reject("the filter removes every trajectory"));
    }
    let order: Vec<usize> = order.into_iter().map(|p| current[p]).collect();
    counts.output_episodes = order.len() as u64;
    Ok(Plan {
        order,
        relabels,
        fates,
        returns,
        counts,
        noise_scale: spec.noise_scale,
        generator,
    })
}

/// DSRL's inpaint step for one range; returns the positions of `order` that remain.
fn inpaint(
    r: &InpaintRange,
    task: &Task,
    cost: &[f32],
    reward: &[f32],
    order: &[usize],
) -> Result<Vec<usize>, FilterError> {
    let (c0, c1) = (task.min_episode_cost, task.max_episode_cost);
    let (lo_c, hi_c) = (Threshold((c1 - c0) * r.pcmin + c0), Threshold((c1 - c0) * r.pcmax + c0));
    let in_band: Vec<bool> = order.iter().map(|&p| lo_c.le(cost[p]) && hi_c.ge(cost[p])).collect();
    let band: Vec<f32> = order
        .iter()
        .zip(&in_band)
        .filter(|(_, b)| **b)
        .map(|(&p, _)| reward[p])
        .collect();
    if band.is_empty() {
        return Err(reject(format!(
            "no trajectory has a cost return in the inpaint band [{}, {}]",
            lo_c.0, hi_c.0
        )));
    }
    let rmin = band.iter().copied().fold(f32::INFINITY, f32::min);
    let rmax = band.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    // (rmax - rmin) is a float32 scalar; times a Python float and plus a float32 scalar, float64.
    let span = (rmax - rmin) as f64;
    let (lo_r, hi_r) = (
        Threshold(span * r.prmin + rmin as f64),
        Threshold(span * r.prmax + rmin as f64),
    );
    Ok(order
        .iter()
        .zip(&in_band)
        .filter(|(p, band)| !(**band && lo_r.le(reward[**p]) && hi_r.ge(reward[**p])))
        .map(|(&p, _)| p)
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use dsrl_suite::catalog::Catalog;

    fn task() -> Task {
        Catalog::embedded().unwrap().get("OfflineCarCircle-v0").unwrap().clone()
    }

    fn episodes(returns: &[(f32, f32, u32)]) -> Vec<EpisodeSummary> {
        let mut start = 0;
        returns
            .iter()
            .map(|&(c, r, length)| {
                let e = EpisodeSummary {
                    start,
                    length,
                    reward_return: r,
                    cost_return: c,
                };
                start += length as u64;
                e
            })
            .collect()
    }

    fn spec(text: &str) -> FilterSpec {
        FilterSpec::parse(text, &task()).unwrap().unwrap()
    }

    #[test]
    fn equal_cost_returns_give_a_zero_width_grid_and_a_refusal() {
        let eps = episodes(&[(0.0, 10.0, 300), (0.0, 20.0, 300), (0.0, 30.0, 300)]);
        let err = plan(&spec("density=0.5"), &task(), &eps).unwrap_err();
        assert!(err.about_data);
        assert!(err.to_string().contains("zero width"), "{err}");
    }

    #[test]
    fn outliers_with_more_unit_costs_than_steps_are_refused() {
        // Every trajectory is a candidate (cost >= 50, reward >= 267.2) but only 3 steps long; target_cost 100
        // draws outlier cost returns up to 99.
        let eps = episodes(&[(60.0, 400.0, 3); 40]);
        let err = plan(&spec("noise=0.5,target_cost=100"), &task(), &eps).unwrap_err();
        assert!(err.to_string().contains("more unit costs than steps"), "{err}");
    }

    #[test]
    fn counts_and_fates_add_up() {
        let eps = episodes(&[
            (5.0, 100.0, 300),
            (60.0, 450.0, 300),
            (80.0, 500.0, 300),
            (15.0, 200.0, 300),
        ]);
        let p = plan(&spec("noise=0.25,epsilon=150,target_cost=20"), &task(), &eps).unwrap();
        // Candidates for the one outlier (int(4 * 0.25)): episodes 1 and 2 (cost >= 50, reward >= 267.2). The
        // outlier gets a cost return below 20 and 1.5x its reward (675 or 750), so it becomes the best safe
        // trajectory, and epsilon=150 removes exactly it (episode 3's 200 is far below).
        assert_eq!(p.counts.relabelled_outliers, 1);
        assert_eq!(p.counts.removed_by_epsilon, 1);
        let removed: Vec<usize> = (0..4).filter(|&e| p.fates[e] == Fate::RemovedByEpsilon).collect();
        assert!(removed == [1] || removed == [2], "{removed:?}");
        assert!(p.relabels.contains_key(&removed[0]));
        assert_eq!(p.counts.output_episodes, 3);
        assert_eq!(p.order.len(), 3);
        assert!(
            p.order.windows(2).all(|w| w[0] < w[1]),
            "epsilon sorts like np.setdiff1d"
        );
    }
}
