//! The leaderboard's arithmetic: ranking entries on a task, and aggregating normalized scores across tasks with
//! the interquartile mean and a seeded percentile-bootstrap confidence interval (Agarwal et al. 2021, "rliable").

use serde::{Deserialize, Serialize};

use crate::filters::pyrandom::PyRandom;
use crate::score::NormalizedScore;

/// Orders entries for a task's table: safe entries (normalized cost ≤ 1) by normalized reward, highest first; then
/// the unsafe ones, the least violating first (normalized cost, then reward). Returns indices into `scores`; ties
/// keep submission order.
pub fn rank(scores: &[NormalizedScore]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..scores.len()).collect();
    order.sort_by(|&a, &b| {
        let (x, y) = (&scores[a], &scores[b]);
        match (x.is_safe(), y.is_safe()) {
            (true, false) => std::cmp::Ordering::Less,
            (false, true) => std::cmp::Ordering::Greater,
            (true, true) => y.reward.total_cmp(&x.reward),
            (false, false) => x.cost.total_cmp(&y.cost).then(y.reward.total_cmp(&x.reward)),
        }
    });
    order
}

/// The interquartile mean: the mean of the values left after dropping the lowest and highest quarter
/// (`floor(n/4)` from each end, SciPy's `trim_mean(x, 0.25)`). `None` for no values.
pub fn interquartile_mean(values: &[f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let cut = sorted.len() / 4;
    let middle = &sorted[cut..sorted.len() - cut];
    Some(middle.iter().sum::<f64>() / middle.len() as f64)
}

/// An aggregate with its confidence interval and how it was drawn.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Interval {
    pub estimate: f64,
    pub low: f64,
    pub high: f64,
    pub confidence: f64,
    pub resamples: u32,
    pub seed: u64,
}

/// The IQM of `values` (one per task) with a percentile-bootstrap interval: `resamples` draws of as many values
/// with replacement (CPython's `random` seeded with `seed`), the IQM of each, and their `(1 ± confidence)/2`
/// quantiles (linear interpolation, NumPy's default).
pub fn iqm_with_interval(values: &[f64], resamples: u32, confidence: f64, seed: u64) -> Option<Interval> {
    let estimate = interquartile_mean(values)?;
    let mut random = PyRandom::seed(seed);
    let mut draws: Vec<f64> = (0..resamples.max(1))
        .map(|_| {
            let sample: Vec<f64> = (0..values.len())
                .map(|_| values[random.randbelow(values.len())])
                .collect();
            interquartile_mean(&sample).expect("non-empty")
        })
        .collect();
    draws.sort_by(f64::total_cmp);
    let quantile = |q: f64| {
        let pos = q * (draws.len() - 1) as f64;
        let (i, frac) = (pos.floor() as usize, pos - pos.floor());
        let next = draws[(i + 1).min(draws.len() - 1)];
        draws[i] + frac * (next - draws[i])
    };
    Some(Interval {
        estimate,
        low: quantile((1.0 - confidence) / 2.0),
        high: quantile((1.0 + confidence) / 2.0),
        confidence,
        resamples: resamples.max(1),
        seed,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn score(reward: f64, cost: f64) -> NormalizedScore {
        NormalizedScore { reward, cost }
    }

    #[test]
    fn safe_entries_rank_by_reward_before_every_unsafe_one() {
        let scores = [
            score(0.9, 1.5), // unsafe, high reward
            score(0.3, 0.2),
            score(0.6, 1.0), // safe at exactly 1
            score(0.8, 3.0),
            score(0.2, 1.2),
        ];
        assert_eq!(rank(&scores), vec![2, 1, 4, 0, 3]);
        assert!(rank(&[]).is_empty());
    }

    #[test]
    fn iqm_trims_a_quarter_from_each_end() {
        assert_eq!(interquartile_mean(&[]), None);
        assert_eq!(interquartile_mean(&[5.0]), Some(5.0));
        // 8 values: drop 2 from each end -> mean of 3, 4, 5, 6.
        assert_eq!(interquartile_mean(&[8.0, 1.0, 7.0, 2.0, 6.0, 3.0, 5.0, 4.0]), Some(4.5));
        // 5 values: floor(5/4) = 1 from each end; an outlier does not move it.
        assert_eq!(interquartile_mean(&[1.0, 2.0, 3.0, 4.0, 1000.0]), Some(3.0));
    }

    #[test]
    fn the_bootstrap_interval_brackets_the_estimate_and_repeats_with_its_seed() {
        let values: Vec<f64> = (0..12).map(|i| f64::from(i) / 10.0).collect();
        let a = iqm_with_interval(&values, 2000, 0.95, 7).unwrap();
        assert!(a.low < a.estimate && a.estimate < a.high, "{a:?}");
        assert!(a.high - a.low < 0.6, "{a:?}");
        assert_eq!(iqm_with_interval(&values, 2000, 0.95, 7).unwrap(), a);
        assert_ne!(iqm_with_interval(&values, 2000, 0.95, 8).unwrap(), a);
        // Identical values leave no uncertainty.
        let flat = iqm_with_interval(&[0.4; 6], 100, 0.95, 1).unwrap();
        assert_eq!((flat.low, flat.estimate, flat.high), (0.4, 0.4, 0.4));
    }
}
