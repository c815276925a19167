//! CDT's return augmentation (OSRL `augmentation`, spec 5.4): extra trajectories whose reward- and cost-to-go are
//! relabelled towards the data's Pareto frontier, so the model sees (reward, cost) targets it is later asked for.
//!
//! 1. The trajectories' (cost return, reward return) points are thinned on a grid (10 cost × 50 reward bins over
//!    the data's range; more than 10 per bin are sampled down to 10, bins of 2 or fewer are dropped).
//! 2. The Pareto front of the kept points (lower cost, higher reward) is fitted with a polynomial `f` of the task's
//!    degree (`deg` in `data/cdt_targets.csv`).
//! 3. `m = ⌊percent · kept⌋` targets: costs `c_k` evenly spaced over the kept points' cost range, rewards
//!    `r_k ~ U(f(c_k) + min_reward, max_reward)`.
//! 4. Each target takes the nearest kept trajectory (Euclidean, raw returns) whose cost is at most `c_k`; when that
//!    trajectory was taken already, one among those with cost at most its own and reward at least its own minus
//!    `max_rew_decrease`, drawn with probability ∝ 1/(distance + β).
//! 5. The taken trajectory is relabelled: its whole reward-to-go shifted by `r_k − R`, its cost-to-go by `c_k − C`;
//!    states, actions and per-step costs are unchanged.
//!
//! Draws come from the learner's seeded generator. OSRL uses Python's and NumPy's generators and, for repeated
//! picks, pairs targets with trajectories in a regrouped order (a quirk, spec 5.4); neither is reproduced.

use dsrl_policy::noise::Noise;

/// The per-task constants of OSRL's CDT configs, and the fixed grid.
#[derive(Debug, Clone, PartialEq)]
pub struct Augmentation {
    pub percent: f64,
    pub deg: usize,
    pub max_reward: f64,
    pub min_reward: f64,
    pub max_rew_decrease: f64,
    pub beta: f64,
    pub cost_bins: usize,
    pub reward_bins: usize,
    pub max_per_bin: usize,
    pub min_per_bin: usize,
}

impl Augmentation {
    /// OSRL's base config (augment 20%, β 1, grid 10 × 50, 2 < per bin ≤ 10) with a task's constants.
    pub fn osrl(deg: usize, max_reward: f64, min_reward: f64, max_rew_decrease: f64) -> Augmentation {
        Augmentation {
            percent: 0.2,
            deg,
            max_reward,
            min_reward,
            max_rew_decrease,
            beta: 1.0,
            cost_bins: 10,
            reward_bins: 50,
            max_per_bin: 10,
            min_per_bin: 2,
        }
    }
}

/// One relabelled copy: the trajectory it copies and the (cost, reward) returns it starts out with.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Relabelled {
    pub trajectory: usize,
    pub cost_return: f64,
    pub reward_return: f64,
}

/// The grid thinning of step 1: positions of the kept points.
fn grid_thin(points: &[(f64, f64)], a: &Augmentation, noise: &mut Noise) -> Vec<usize> {
    let range = |f: fn(&(f64, f64)) -> f64| {
        let v = points.iter().map(f);
        (
            v.clone().fold(f64::INFINITY, f64::min),
            v.fold(f64::NEG_INFINITY, f64::max),
        )
    };
    let ((c0, c1), (r0, r1)) = (range(|p| p.0), range(|p| p.1));
    let bin = |x: f64, lo: f64, hi: f64, bins: usize| {
        if hi > lo {
            (((x - lo) / ((hi - lo) / bins as f64)).floor() as usize).min(bins)
        } else {
            0
        }
    };
    let mut bins: std::collections::BTreeMap<(usize, usize), Vec<usize>> = Default::default();
    for (i, &(c, r)) in points.iter().enumerate() {
        bins.entry((bin(c, c0, c1, a.cost_bins), bin(r, r0, r1, a.reward_bins)))
            .or_default()
            .push(i);
    }
    let mut kept = Vec::new();
    for (_, mut members) in bins {
        if members.len() > a.max_per_bin {
            // A partial Fisher–Yates shuffle: a uniform sample of max_per_bin members.
            for k in 0..a.max_per_bin {
                let j = k + (noise.next_u64() % (members.len() - k) as u64) as usize;
                members.swap(k, j);
            }
            members.truncate(a.max_per_bin);
            kept.extend(members);
        } else if members.len() > a.min_per_bin {
            kept.extend(members);
        }
    }
    kept.sort_unstable();
    kept
}

/// The Pareto front (lowest cost for each reward level): points no other point beats on both.
fn pareto_front(points: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let mut sorted = points.to_vec();
    sorted.sort_by(|a, b| a.0.total_cmp(&b.0).then(b.1.total_cmp(&a.1)));
    let mut front: Vec<(f64, f64)> = Vec::new();
    for p in sorted {
        if front.last().is_none_or(|last| p.1 > last.1) {
            front.push(p);
        }
    }
    front
}

/// Least-squares polynomial coefficients (constant first) of degree at most `deg` through `points`.
// Elimination on a (deg + 1)² system reads clearest with row and column indices.
#[allow(clippy::needless_range_loop)]
pub fn polyfit(points: &[(f64, f64)], deg: usize) -> Vec<f64> {
    let deg = deg.min(points.len().saturating_sub(1));
    let n = deg + 1;
    // Normal equations on x scaled to [−1, 1] for conditioning, then mapped back.
    let (lo, hi) = points
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), p| (l.min(p.0), h.max(p.0)));
    let (mid, half) = ((lo + hi) / 2.0, ((hi - lo) / 2.0).max(1e-12));
    let mut ata = vec![vec![0.0; n]; n];
    let mut atb = vec![0.0; n];
    for &(x, y) in points {
        let t = (x - mid) / half;
        let powers: Vec<f64> = (0..n).map(|k| t.powi(k as i32)).collect();
        for i in 0..n {
            atb[i] += powers[i] * y;
            for j in 0..n {
                ata[i][j] += powers[i] * powers[j];
            }
        }
    }
    // Gaussian elimination with partial pivoting.
    for col in 0..n {
        let pivot = (col..n)
            .max_by(|&a, &b| ata[a][col].abs().total_cmp(&ata[b][col].abs()))
            .unwrap();
        ata.swap(col, pivot);
        atb.swap(col, pivot);
        if ata[col][col].abs() < 1e-300 {
            continue;
        }
        for row in col + 1..n {
            let f = ata[row][col] / ata[col][col];
            for k in col..n {
                ata[row][k] -= f * ata[col][k];
            }
            atb[row] -= f * atb[col];
        }
    }
    let mut scaled = vec![0.0; n];
    for row in (0..n).rev() {
        let s: f64 = (row + 1..n).map(|k| ata[row][k] * scaled[k]).sum();
        scaled[row] = if ata[row][row].abs() < 1e-300 {
            0.0
        } else {
            (atb[row] - s) / ata[row][row]
        };
    }
    // Expand Σ s_k ((x − mid)/half)^k into powers of x.
    let mut coefficients = vec![0.0; n];
    for (k, &s) in scaled.iter().enumerate() {
        // ((x − mid)/half)^k = Σ_j C(k, j) x^j (−mid)^(k−j) / half^k
        let mut binomial = 1.0;
        for j in 0..=k {
            coefficients[j] += s * binomial * (-mid).powi((k - j) as i32) / half.powi(k as i32);
            binomial = binomial * (k - j) as f64 / (j + 1) as f64;
        }
    }
    coefficients
}

fn evaluate(coefficients: &[f64], x: f64) -> f64 {
    coefficients.iter().rev().fold(0.0, |acc, c| acc * x + c)
}

/// The relabelled copies for trajectories with returns `points` ((cost, reward) per trajectory).
pub fn augment(points: &[(f64, f64)], a: &Augmentation, noise: &mut Noise) -> Vec<Relabelled> {
    if points.is_empty() || a.percent <= 0.0 {
        return Vec::new();
    }
    let kept = grid_thin(points, a, noise);
    let m = (a.percent * kept.len() as f64) as usize;
    if m == 0 {
        return Vec::new();
    }
    let kept_points: Vec<(f64, f64)> = kept.iter().map(|&i| points[i]).collect();
    let front = pareto_front(&kept_points);
    let f = polyfit(&front, a.deg);
    let (c_lo, c_hi) = kept_points
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), p| (l.min(p.0), h.max(p.0)));
    let mut used = std::collections::HashSet::new();
    let mut out = Vec::with_capacity(m);
    for k in 0..m {
        let c = if m == 1 {
            c_lo
        } else {
            c_lo + (c_hi - c_lo) * k as f64 / (m - 1) as f64
        };
        let low = evaluate(&f, c) + a.min_reward;
        let r = low + noise.uniform() * (a.max_reward - low);
        let distance = |i: usize| ((points[i].0 - c).powi(2) + (points[i].1 - r).powi(2)).sqrt();
        let Some(nearest) = kept
            .iter()
            .copied()
            .filter(|&i| points[i].0 <= c)
            .min_by(|&x, &y| distance(x).total_cmp(&distance(y)))
        else {
            continue;
        };
        let chosen = if used.insert(nearest) {
            nearest
        } else {
            let (nc, nr) = points[nearest];
            let candidates: Vec<usize> = kept
                .iter()
                .copied()
                .filter(|&i| points[i].0 <= nc && points[i].1 >= nr - a.max_rew_decrease)
                .collect();
            let weights: Vec<f64> = candidates.iter().map(|&i| 1.0 / (distance(i) + a.beta)).collect();
            let total: f64 = weights.iter().sum();
            let mut u = noise.uniform() * total;
            let mut pick = candidates[candidates.len() - 1];
            for (&i, w) in candidates.iter().zip(&weights) {
                if u < *w {
                    pick = i;
                    break;
                }
                u -= w;
            }
            pick
        };
        out.push(Relabelled {
            trajectory: chosen,
            cost_return: c,
            reward_return: r,
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn polyfit_recovers_a_polynomial_and_the_front_keeps_undominated_points() {
        let points: Vec<(f64, f64)> = (0..20)
            .map(|i| i as f64 * 3.0)
            .map(|x| (x, 2.0 - 0.5 * x + 0.01 * x * x))
            .collect();
        let c = polyfit(&points, 2);
        for (got, want) in c.iter().zip([2.0, -0.5, 0.01]) {
            assert!((got - want).abs() < 1e-6, "{c:?}");
        }
        // Degree 0 is the mean; fewer points than the degree lower it.
        assert!((polyfit(&[(0.0, 1.0), (5.0, 3.0)], 0)[0] - 2.0).abs() < 1e-12);
        assert_eq!(polyfit(&[(1.0, 4.0)], 3).len(), 1);
        let front = pareto_front(&[(1.0, 5.0), (2.0, 4.0), (2.0, 9.0), (3.0, 7.0), (0.5, 1.0)]);
        assert_eq!(front, vec![(0.5, 1.0), (1.0, 5.0), (2.0, 9.0)]);
    }

    #[test]
    fn targets_span_the_cost_range_and_relabel_trajectories_within_their_cost() {
        // 400 trajectories on a rising frontier with noise below it.
        let mut noise = Noise::seeded(3);
        let points: Vec<(f64, f64)> = (0..400)
            .map(|_| {
                let c = noise.uniform() * 100.0;
                (c, 5.0 * c - noise.uniform() * 200.0)
            })
            .collect();
        let a = Augmentation::osrl(1, 600.0, 1.0, 100.0);
        let out = augment(&points, &a, &mut Noise::seeded(4));
        assert!(!out.is_empty() && out.len() <= 80, "{}", out.len());
        let costs: Vec<f64> = out.iter().map(|r| r.cost_return).collect();
        assert!(costs.windows(2).all(|w| w[0] <= w[1]), "evenly spaced, ascending");
        for r in &out {
            // A copy never starts out with less cost than the trajectory it relabels has.
            assert!(points[r.trajectory].0 <= r.cost_return + 1e-9, "{r:?}");
            assert!(r.reward_return <= 600.0);
        }
        // Deterministic for a seed.
        assert_eq!(out, augment(&points, &a, &mut Noise::seeded(4)));
    }
}
