//! The leaderboard's arithmetic: ranking entries on a task, and aggregating normalized scores across tasks with
//! the interquartile mean and a seeded percentile-bootstrap confidence interval (Agarwal et al. 2021, "rliable").

use serde::{Deserialize, Serialize};

use dsrl_pynumerics::pyrandom::PyRandom;
use dsrl_suite::catalog::Task;
use dsrl_suite::score::{EpisodeResult, NormalizedScore};

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
    let draws: Vec<f64> = (0..resamples.max(1))
        .map(|_| {
            let sample: Vec<f64> = (0..values.len())
                .map(|_| values[random.randbelow(values.len())])
                .collect();
            interquartile_mean(&sample).expect("non-empty")
        })
        .collect();
    Some(percentile_interval(estimate, draws, confidence, resamples.max(1), seed))
}

/// The interquartile mean over tasks of each task's mean over its training seeds (`per_task`, one value per seed),
/// with a percentile-bootstrap interval: each draw takes as many tasks with replacement and, within each task drawn
/// that has several seeds, as many seeds with replacement (CPython's `random` seeded with `seed`). With one seed
/// per task it draws exactly as `iqm_with_interval` does. NaN estimate for no tasks.
pub fn iqm_over_seeds_with_interval(per_task: &[Vec<f64>], resamples: u32, confidence: f64, seed: u64) -> Interval {
    let mean = |xs: &[f64]| xs.iter().sum::<f64>() / xs.len() as f64;
    let means: Vec<f64> = per_task.iter().map(|seeds| mean(seeds)).collect();
    let estimate = interquartile_mean(&means).unwrap_or(f64::NAN);
    let mut random = PyRandom::seed(seed);
    let resamples = resamples.max(1);
    let draws: Vec<f64> = (0..resamples)
        .map(|_| {
            let sample: Vec<f64> = (0..per_task.len())
                .map(|_| {
                    let task = &per_task[random.randbelow(per_task.len())];
                    if task.len() == 1 {
                        task[0]
                    } else {
                        (0..task.len()).map(|_| task[random.randbelow(task.len())]).sum::<f64>() / task.len() as f64
                    }
                })
                .collect();
            interquartile_mean(&sample).unwrap_or(f64::NAN)
        })
        .collect();
    percentile_interval(estimate, draws, confidence, resamples, seed)
}

/// One threshold's episodes: their count, mean returns and normalized score.
#[derive(Debug, Clone, PartialEq)]
pub struct ThresholdScore {
    pub cost_threshold: f64,
    pub episodes: usize,
    pub mean_reward_return: f64,
    pub mean_cost_return: f64,
    pub score: NormalizedScore,
}

/// Per threshold of `task` (in its order) that has episodes: the mean reward and cost return and their normalized
/// score (spec 4.1: DSRL normalizes the mean returns over a threshold's episodes).
pub fn threshold_scores(task: &Task, episodes: &[EpisodeResult]) -> Vec<ThresholdScore> {
    task.cost_thresholds
        .iter()
        .filter_map(|&threshold| {
            let rows: Vec<&EpisodeResult> = episodes.iter().filter(|e| e.cost_threshold == threshold).collect();
            if rows.is_empty() {
                return None;
            }
            let n = rows.len() as f64;
            let reward = rows.iter().map(|e| e.reward_return).sum::<f64>() / n;
            let cost = rows.iter().map(|e| e.cost_return).sum::<f64>() / n;
            Some(ThresholdScore {
                cost_threshold: threshold,
                episodes: rows.len(),
                mean_reward_return: reward,
                mean_cost_return: cost,
                score: task.normalized_score(reward, cost, threshold),
            })
        })
        .collect()
}

/// An entry's normalized reward and cost: the means over the thresholds of each threshold's normalized score.
/// `None` without episodes.
pub fn entry_score(task: &Task, episodes: &[EpisodeResult]) -> Option<NormalizedScore> {
    let per_threshold = threshold_scores(task, episodes);
    if per_threshold.is_empty() {
        return None;
    }
    let n = per_threshold.len() as f64;
    Some(NormalizedScore {
        reward: per_threshold.iter().map(|t| t.score.reward).sum::<f64>() / n,
        cost: per_threshold.iter().map(|t| t.score.cost).sum::<f64>() / n,
    })
}

/// A percentile-bootstrap interval for one entry on one task, over its episodes: each of `resamples` draws takes, at
/// every threshold, as many episodes with replacement from that threshold's episodes (CPython's `random` seeded
/// with `seed`) and scores them as `entry_score`. Returns the reward and the cost interval around the entry's score.
pub fn entry_interval(
    task: &Task,
    episodes: &[EpisodeResult],
    resamples: u32,
    confidence: f64,
    seed: u64,
) -> Option<(Interval, Interval)> {
    let score = entry_score(task, episodes)?;
    let groups: Vec<Vec<&EpisodeResult>> = task
        .cost_thresholds
        .iter()
        .map(|&k| episodes.iter().filter(|e| e.cost_threshold == k).collect::<Vec<_>>())
        .filter(|g| !g.is_empty())
        .collect();
    let mut random = PyRandom::seed(seed);
    let resamples = resamples.max(1);
    let (mut rewards, mut costs) = (Vec::new(), Vec::new());
    let mut sample = Vec::with_capacity(episodes.len());
    for _ in 0..resamples {
        sample.clear();
        for group in &groups {
            for _ in 0..group.len() {
                sample.push(group[random.randbelow(group.len())].clone());
            }
        }
        let s = entry_score(task, &sample).expect("each resample has episodes");
        rewards.push(s.reward);
        costs.push(s.cost);
    }
    let interval = |estimate, draws| percentile_interval(estimate, draws, confidence, resamples, seed);
    Some((interval(score.reward, rewards), interval(score.cost, costs)))
}

/// The mean over training seeds of one method's entries on one task (each seed's `entry_score`), with a
/// percentile-bootstrap interval that includes seed variance: each of `resamples` draws takes as many seeds with
/// replacement, then, within each seed drawn, every threshold's episodes with replacement (stratified, as rliable
/// resamples runs and then tasks), and averages the seeds' scores. Returns the reward and the cost interval around
/// the mean; `None` without seeds or with a seed that has no episodes.
pub fn seeds_interval(
    task: &Task,
    seeds: &[Vec<EpisodeResult>],
    resamples: u32,
    confidence: f64,
    seed: u64,
) -> Option<(Interval, Interval)> {
    let scores: Vec<NormalizedScore> = seeds.iter().map(|e| entry_score(task, e)).collect::<Option<_>>()?;
    if scores.is_empty() {
        return None;
    }
    let n = scores.len();
    let mean = |xs: &mut dyn Iterator<Item = f64>| xs.sum::<f64>() / n as f64;
    let (reward, cost) = (
        mean(&mut scores.iter().map(|s| s.reward)),
        mean(&mut scores.iter().map(|s| s.cost)),
    );
    // Each seed's episodes grouped by threshold, once.
    let groups: Vec<Vec<Vec<&EpisodeResult>>> = seeds
        .iter()
        .map(|episodes| {
            task.cost_thresholds
                .iter()
                .map(|&k| episodes.iter().filter(|e| e.cost_threshold == k).collect::<Vec<_>>())
                .filter(|g| !g.is_empty())
                .collect()
        })
        .collect();
    let mut random = PyRandom::seed(seed);
    let resamples = resamples.max(1);
    let (mut rewards, mut costs) = (
        Vec::with_capacity(resamples as usize),
        Vec::with_capacity(resamples as usize),
    );
    let mut sample = Vec::new();
    for _ in 0..resamples {
        let (mut r, mut c) = (0.0, 0.0);
        for _ in 0..n {
            let drawn = &groups[random.randbelow(n)];
            sample.clear();
            for group in drawn {
                for _ in 0..group.len() {
                    sample.push(group[random.randbelow(group.len())].clone());
                }
            }
            let s = entry_score(task, &sample).expect("each drawn seed has episodes");
            r += s.reward;
            c += s.cost;
        }
        rewards.push(r / n as f64);
        costs.push(c / n as f64);
    }
    let interval = |estimate, draws| percentile_interval(estimate, draws, confidence, resamples, seed);
    Some((interval(reward, rewards), interval(cost, costs)))
}

/// The interval around `estimate` that `draws` (the bootstrap's statistics) give: their `(1 ± confidence)/2`
/// quantiles, with how they were drawn.
fn percentile_interval(estimate: f64, mut draws: Vec<f64>, confidence: f64, resamples: u32, seed: u64) -> Interval {
    draws.sort_by(f64::total_cmp);
    Interval {
        estimate,
        low: quantile(&draws, (1.0 - confidence) / 2.0),
        high: quantile(&draws, (1.0 + confidence) / 2.0),
        confidence,
        resamples,
        seed,
    }
}

/// The `q` quantile of sorted `draws` with linear interpolation (NumPy's default); `q = 0.5` is the median.
pub fn quantile(draws: &[f64], q: f64) -> f64 {
    let pos = q * (draws.len() - 1) as f64;
    let (i, frac) = (pos.floor() as usize, pos - pos.floor());
    let next = draws[(i + 1).min(draws.len() - 1)];
    draws[i] + frac * (next - draws[i])
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

    #[test]
    fn an_entry_on_one_task_gets_an_interval_over_its_episodes() {
        let catalog = dsrl_suite::catalog::Catalog::embedded().unwrap();
        let task = catalog.get("OfflineBallRun-v0").unwrap();
        let episodes: Vec<EpisodeResult> = task
            .cost_thresholds
            .iter()
            .flat_map(|&k| {
                (0..20).map(move |i| EpisodeResult {
                    cost_threshold: k,
                    episode: i,
                    reward_return: 300.0 + 10.0 * f64::from(i),
                    cost_return: f64::from(i % 7),
                    length: 100,
                })
            })
            .collect();
        let score = entry_score(task, &episodes).unwrap();
        let (reward, cost) = entry_interval(task, &episodes, 500, 0.95, 0).unwrap();
        assert_eq!((reward.estimate, cost.estimate), (score.reward, score.cost));
        assert!(
            reward.low < reward.estimate && reward.estimate < reward.high,
            "{reward:?}"
        );
        assert!(cost.low < cost.estimate && cost.estimate < cost.high, "{cost:?}");
        assert_eq!(entry_interval(task, &episodes, 500, 0.95, 0).unwrap().0, reward);
        // Identical episodes: the interval is the point.
        let same: Vec<EpisodeResult> = episodes
            .iter()
            .map(|e| EpisodeResult {
                reward_return: 1.0,
                cost_return: 2.0,
                ..e.clone()
            })
            .collect();
        let (r, c) = entry_interval(task, &same, 100, 0.95, 0).unwrap();
        assert_eq!(
            (r.low, r.high, c.low, c.high),
            (r.estimate, r.estimate, c.estimate, c.estimate)
        );
        assert!(entry_score(task, &[]).is_none());
    }

    /// Seeds whose means differ widely give an interval wider than any one seed's episode-only interval.
    #[test]
    fn an_interval_over_seeds_that_differ_is_wider_than_any_seeds() {
        let catalog = dsrl_suite::catalog::Catalog::embedded().unwrap();
        let task = catalog.get("OfflineBallRun-v0").unwrap();
        // Three seeds, 10 episodes per threshold, cost returns spread ±2 around 5, 30 and 60 (a CPQ-like spread).
        let seed_episodes = |centre: f64| -> Vec<EpisodeResult> {
            task.cost_thresholds
                .iter()
                .flat_map(|&k| {
                    (0..10).map(move |i| EpisodeResult {
                        cost_threshold: k,
                        episode: i,
                        reward_return: 400.0 + i as f64,
                        cost_return: centre + (i as f64 - 4.5) * 0.4,
                        length: 100,
                    })
                })
                .collect()
        };
        let seeds = vec![seed_episodes(5.0), seed_episodes(30.0), seed_episodes(60.0)];
        let (_, cost) = seeds_interval(task, &seeds, 1000, 0.95, 3).unwrap();
        let means: Vec<f64> = seeds.iter().map(|e| entry_score(task, e).unwrap().cost).collect();
        assert!((cost.estimate - means.iter().sum::<f64>() / 3.0).abs() < 1e-12);
        for episodes in &seeds {
            let (_, one) = entry_interval(task, episodes, 1000, 0.95, 3).unwrap();
            assert!(
                cost.high - cost.low > one.high - one.low,
                "over seeds [{}, {}] is not wider than one seed's [{}, {}]",
                cost.low,
                cost.high,
                one.low,
                one.high
            );
        }
        // Deterministic for a seed.
        assert_eq!(seeds_interval(task, &seeds, 1000, 0.95, 3).unwrap().1, cost);
        assert!(seeds_interval(task, &[], 10, 0.95, 3).is_none());
    }

    /// One seed per task draws as the plain IQM bootstrap; several seeds widen the interval.
    #[test]
    fn the_family_aggregate_over_seeds_reduces_to_the_iqm_with_one_seed() {
        let values = [0.1, 0.5, 0.9, 0.3, 0.7, 0.2, 0.8, 0.4];
        let one: Vec<Vec<f64>> = values.iter().map(|v| vec![*v]).collect();
        assert_eq!(
            iqm_over_seeds_with_interval(&one, 500, 0.95, 4),
            iqm_with_interval(&values, 500, 0.95, 4).unwrap()
        );
        // The same task means, each from two seeds ±0.3 apart: same estimate, a wider interval.
        let spread: Vec<Vec<f64>> = values.iter().map(|v| vec![v - 0.3, v + 0.3]).collect();
        let (a, b) = (
            iqm_over_seeds_with_interval(&one, 500, 0.95, 4),
            iqm_over_seeds_with_interval(&spread, 500, 0.95, 4),
        );
        assert!((a.estimate - b.estimate).abs() < 1e-12);
        assert!(b.high - b.low > a.high - a.low, "{b:?} is not wider than {a:?}");
    }
}
