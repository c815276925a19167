//! Running observation normalization for the expert, opt-in per recipe (`observation_normalization = true`).
//!
//! Why: on the velocity tasks the observations mix joint angles (~0.1) with joint velocities (~10). Without
//! normalization our PPO-Lagrangian expert learned HalfCheetah only to ~1.5 m/s in 3M steps (data/README), never
//! fast enough to pay the speed cost for reward, so no trajectory reached DSRL's tempting corner. Normalizing the
//! inputs by running statistics is what MuJoCo PPO baselines do (tianshou's, among them); the paper's FSRL experts do
//! not, so it is a recorded departure, made for compute.
//!
//! The statistics are frozen while a collect plays and while the learner updates on it (the stored
//! log-probabilities stay those of the acting policy), then take in that collect's observations. The exported
//! expert declares them as the policy format's `(obs − mean) / std`, so it acts exactly as it did in training.

use serde::{Deserialize, Serialize};

/// Floor on a feature's standard deviation: a feature that was constant so far (its variance 0) must not blow up
/// to huge inputs the first time it moves.
const MIN_STD: f64 = 1e-2;

/// Mean and (population) variance per feature of every observation seen, and how many.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObservationStats {
    pub count: f64,
    pub mean: Vec<f64>,
    pub var: Vec<f64>,
}

impl ObservationStats {
    /// No observation yet: the identity (mean 0, std 1).
    pub fn new(dim: usize) -> ObservationStats {
        ObservationStats {
            count: 0.0,
            mean: vec![0.0; dim],
            var: vec![1.0; dim],
        }
    }

    pub fn dim(&self) -> usize {
        self.mean.len()
    }

    /// Takes in row-major `rows` of `dim()` features (Chan et al.'s pairwise combination of the two moments).
    pub fn observe(&mut self, rows: &[f32]) {
        let d = self.dim();
        let n = rows.len() / d.max(1);
        if n == 0 {
            return;
        }
        let n_f = n as f64;
        let mut batch_mean = vec![0.0; d];
        for row in rows.chunks_exact(d) {
            for (m, x) in batch_mean.iter_mut().zip(row) {
                *m += f64::from(*x);
            }
        }
        batch_mean.iter_mut().for_each(|m| *m /= n_f);
        let mut batch_var = vec![0.0; d];
        for row in rows.chunks_exact(d) {
            for ((v, m), x) in batch_var.iter_mut().zip(&batch_mean).zip(row) {
                *v += (f64::from(*x) - m).powi(2);
            }
        }
        batch_var.iter_mut().for_each(|v| *v /= n_f);
        if self.count == 0.0 {
            self.mean = batch_mean;
            self.var = batch_var;
        } else {
            let total = self.count + n_f;
            for i in 0..d {
                let delta = batch_mean[i] - self.mean[i];
                let m2 = self.var[i] * self.count + batch_var[i] * n_f + delta * delta * self.count * n_f / total;
                self.mean[i] += delta * n_f / total;
                self.var[i] = m2 / total;
            }
        }
        self.count += n_f;
    }

    /// The `(mean, std)` the policy format declares.
    pub fn mean_and_std(&self) -> (Vec<f32>, Vec<f32>) {
        let mean = self.mean.iter().map(|&m| m as f32).collect();
        let std = self.var.iter().map(|&v| v.sqrt().max(MIN_STD) as f32).collect();
        (mean, std)
    }

    /// `(obs − mean) / std` of row-major observations, in the same f32 arithmetic as a loaded policy.
    pub fn apply(&self, rows: &[f32]) -> Vec<f32> {
        let (mean, std) = self.mean_and_std();
        let d = self.dim();
        rows.chunks(d)
            .flat_map(|row| row.iter().zip(mean.iter().zip(&std)).map(|(x, (m, s))| (x - m) / s))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batches_combine_to_the_moments_of_all_the_rows() {
        // Two features over 7 rows, taken in as batches of 3 and 4.
        let rows: Vec<f32> = (0..14).map(|i| ((i * 37) % 11) as f32 * 0.5 - 1.0).collect();
        let mut stats = ObservationStats::new(2);
        assert_eq!(stats.apply(&rows), rows, "no observation yet is the identity");
        stats.observe(&rows[..6]);
        stats.observe(&rows[6..]);
        assert_eq!(stats.count, 7.0);
        for f in 0..2 {
            let xs: Vec<f64> = rows.iter().skip(f).step_by(2).map(|&x| f64::from(x)).collect();
            let mean = xs.iter().sum::<f64>() / 7.0;
            let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / 7.0;
            assert!((stats.mean[f] - mean).abs() < 1e-12, "mean of feature {f}");
            assert!((stats.var[f] - var).abs() < 1e-12, "variance of feature {f}");
        }
        let normalized = stats.apply(&rows);
        for f in 0..2 {
            let zs: Vec<f64> = normalized.iter().skip(f).step_by(2).map(|&z| f64::from(z)).collect();
            assert!(zs.iter().sum::<f64>().abs() < 1e-5, "normalized feature {f} has mean 0");
            assert!(
                (zs.iter().map(|z| z * z).sum::<f64>() / 7.0 - 1.0).abs() < 1e-5,
                "and variance 1"
            );
        }
    }

    #[test]
    fn a_constant_feature_is_floored_not_divided_by_zero() {
        let mut stats = ObservationStats::new(1);
        stats.observe(&[3.0, 3.0, 3.0]);
        assert_eq!(stats.mean_and_std().1, vec![MIN_STD as f32]);
        assert_eq!(stats.apply(&[3.0, 3.5]), vec![0.0, 0.5 / MIN_STD as f32]);
    }
}
