//! The Gaussian actor of DSRL's experts (FSRL `ActorProbLargeVar`, spec 6.1): the mean is `max_action · tanh(MLP(obs))`,
//! the standard deviation a state-independent parameter `exp(log_std)` initialised at `exp(−0.5)`; sampled actions
//! are clipped to the action bounds by the environment (`action_bound_method="clip"`), and the log-probability is
//! that of the unclipped sample. The squashed variant (`tanh` of a Gaussian sample, SAC-style actors) is here too.

use candle_core::{D, DType, Device, Tensor, Var};

use crate::Result;
use crate::mlp::{Activation, Mlp};
use crate::noise::Noise;

const HALF_LN_TAU: f64 = 0.918_938_533_204_672_7; // ½·ln(2π)

pub struct GaussianActor {
    pub mean_net: Mlp,
    pub log_std: Var,
    pub max_action: f64,
}

impl GaussianActor {
    pub const LOG_STD_INIT: f32 = -0.5;

    pub fn new(
        obs_dim: usize,
        act_dim: usize,
        hidden: &[usize],
        activation: Activation,
        max_action: f64,
        noise: &mut Noise,
    ) -> Result<GaussianActor> {
        let sizes = crate::mlp::layer_sizes(obs_dim, hidden, act_dim);
        Ok(GaussianActor {
            mean_net: Mlp::orthogonal("actor.mu", &sizes, activation, 1.0, 1.0, noise)?,
            log_std: Var::from_vec(vec![Self::LOG_STD_INIT; act_dim], act_dim, &Device::Cpu)?,
            max_action,
        })
    }

    /// `[batch, act_dim]` means for `[batch, obs_dim]` observations.
    pub fn mean(&self, obs: &Tensor) -> Result<Tensor> {
        Ok(self.mean_net.forward(obs)?.tanh()?.affine(self.max_action, 0.0)?)
    }

    /// Samples one action per row of `obs` (row-major `[batch, act_dim]`), unclipped.
    pub fn sample(&self, obs: &Tensor, noise: &mut Noise) -> Result<Vec<f32>> {
        let mean = self.mean(obs)?.flatten_all()?.to_vec1::<f32>()?;
        let std: Vec<f32> = self.log_std.as_tensor().exp()?.to_vec1::<f32>()?;
        let eps = noise.normals_f32(mean.len());
        Ok(mean
            .iter()
            .zip(&eps)
            .enumerate()
            .map(|(i, (m, e))| m + std[i % std.len()] * e)
            .collect())
    }

    /// Samples as [`GaussianActor::sample`] with each sample's log-probability, computed from the same noise
    /// (`Σ −½ε² − log σ − ½ ln 2π`) without another pass through the network.
    pub fn sample_with_log_prob(&self, obs: &Tensor, noise: &mut Noise) -> Result<(Vec<f32>, Vec<f32>)> {
        let mean = self.mean(obs)?.flatten_all()?.to_vec1::<f32>()?;
        let log_std: Vec<f32> = self.log_std.as_tensor().to_vec1::<f32>()?;
        let act_dim = log_std.len();
        let eps = noise.normals_f32(mean.len());
        let actions = mean
            .iter()
            .zip(&eps)
            .enumerate()
            .map(|(i, (m, e))| m + log_std[i % act_dim].exp() * e)
            .collect();
        let log_probs = eps
            .chunks(act_dim)
            .map(|row| {
                row.iter()
                    .zip(&log_std)
                    .map(|(e, ls)| -0.5 * f64::from(*e).powi(2) - f64::from(*ls) - HALF_LN_TAU)
                    .sum::<f64>() as f32
            })
            .collect();
        Ok((actions, log_probs))
    }

    /// Log-probabilities `[batch]` of `actions` under the policy at `obs`.
    pub fn log_prob(&self, obs: &Tensor, actions: &Tensor) -> Result<Tensor> {
        gaussian_log_prob(actions, &self.mean(obs)?, self.log_std.as_tensor())
    }

    pub fn named_vars(&self) -> Vec<(String, Var)> {
        let mut vars = self.mean_net.named_vars();
        vars.push(("actor.log_std".into(), self.log_std.clone()));
        vars
    }

    pub fn to_device(self, device: &Device) -> Result<GaussianActor> {
        Ok(GaussianActor {
            mean_net: self.mean_net.to_device(device)?,
            log_std: crate::var_on(&self.log_std, device)?,
            ..self
        })
    }
}

/// Σ_d log N(x_d; μ_d, σ_d) per row: `x`, `mean` `[batch, dims]`, `log_std` `[dims]`.
pub fn gaussian_log_prob(x: &Tensor, mean: &Tensor, log_std: &Tensor) -> Result<Tensor> {
    let z = x.sub(mean)?.broadcast_div(&log_std.exp()?)?;
    let per_dim = z.sqr()?.affine(-0.5, -HALF_LN_TAU)?.broadcast_sub(log_std)?;
    Ok(per_dim.sum(D::Minus1)?)
}

/// Log-probability of `a = tanh(u)` where `u ~ N(mean, exp(log_std))`, given the pre-squash sample `u`:
/// `log N(u) − Σ log(1 − tanh²(u))`, with `log(1 − tanh²(u)) = 2·(ln 2 − u − softplus(−2u))` for stability.
pub fn squashed_gaussian_log_prob(u: &Tensor, mean: &Tensor, log_std: &Tensor) -> Result<Tensor> {
    let base = gaussian_log_prob(u, mean, log_std)?;
    let minus_2u = u.affine(-2.0, 0.0)?;
    // softplus(x) = max(x, 0) + ln(1 + e^{−|x|})
    let softplus = minus_2u
        .relu()?
        .add(&minus_2u.abs()?.neg()?.exp()?.affine(1.0, 1.0)?.log()?)?;
    let log_jacobian = u.neg()?.sub(&softplus)?.affine(2.0, 2.0 * std::f64::consts::LN_2)?;
    Ok(base.sub(&log_jacobian.sum(D::Minus1)?)?)
}

/// A `[rows, cols]` f32 tensor from row-major values.
pub fn matrix(values: &[f32], rows: usize, cols: usize) -> Result<Tensor> {
    Ok(Tensor::from_slice(values, (rows, cols), &Device::Cpu)?.to_dtype(DType::F32)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t(values: &[f32], rows: usize, cols: usize) -> Tensor {
        matrix(values, rows, cols).unwrap()
    }

    #[test]
    fn gaussian_log_prob_is_the_hand_worked_density() {
        // Two dims: x = (0.5, −1), μ = (0.2, 0), log σ = (−0.5, 0.3).
        let got = gaussian_log_prob(
            &t(&[0.5, -1.0], 1, 2),
            &t(&[0.2, 0.0], 1, 2),
            &Tensor::new(&[-0.5f32, 0.3], &Device::Cpu).unwrap(),
        )
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()[0];
        let term = |x: f64, m: f64, ls: f64| {
            -0.5 * ((x - m) / ls.exp()).powi(2) - ls - 0.5 * (2.0 * std::f64::consts::PI).ln()
        };
        let want = term(0.5, 0.2, -0.5) + term(-1.0, 0.0, 0.3);
        assert!((f64::from(got) - want).abs() < 1e-5, "{got} vs {want}");
    }

    #[test]
    fn squashed_gaussian_density_integrates_to_one_over_the_action_interval() {
        // p_a(a) = p_u(atanh a) / (1 − a²): its integral over (−1, 1) is 1, and each value must match the
        // change of variables computed directly.
        let (mean, log_std) = (0.4f32, 0.2f32);
        let n = 20_000;
        let mut total = 0.0f64;
        let us: Vec<f32> = (0..n)
            .map(|i| {
                let a = -1.0 + (i as f64 + 0.5) * 2.0 / n as f64;
                a.atanh() as f32
            })
            .collect();
        let logp = squashed_gaussian_log_prob(
            &t(&us, n, 1),
            &t(&vec![mean; n], n, 1),
            &Tensor::new(&[log_std], &Device::Cpu).unwrap(),
        )
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
        for (i, lp) in logp.iter().enumerate() {
            let a = (us[i] as f64).tanh();
            let sigma = f64::from(log_std).exp();
            let direct = -0.5 * ((f64::from(us[i]) - f64::from(mean)) / sigma).powi(2)
                - sigma.ln()
                - HALF_LN_TAU
                - (1.0 - a * a).ln();
            if a.abs() < 0.999 {
                assert!((f64::from(*lp) - direct).abs() < 1e-3, "a={a}: {lp} vs {direct}");
            }
            total += f64::from(*lp).exp() * 2.0 / n as f64;
        }
        assert!((total - 1.0).abs() < 1e-3, "integral {total}");
    }

    #[test]
    fn sampled_log_probs_equal_the_density_of_the_sampled_actions() {
        let mut noise = Noise::seeded(4);
        let actor = GaussianActor::new(3, 2, &[8], Activation::Tanh, 1.0, &mut noise).unwrap();
        let obs = t(&[0.1, 0.2, 0.3, -1.0, 0.5, 2.0], 2, 3);
        let (actions, log_probs) = actor.sample_with_log_prob(&obs, &mut noise).unwrap();
        let direct = actor
            .log_prob(&obs, &t(&actions, 2, 2))
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        for (a, b) in log_probs.iter().zip(&direct) {
            assert!((a - b).abs() < 1e-5, "{log_probs:?} vs {direct:?}");
        }
    }

    #[test]
    fn actor_starts_with_log_std_minus_half_and_bounded_means() {
        let mut noise = Noise::seeded(11);
        let actor = GaussianActor::new(3, 2, &[16, 16], Activation::Tanh, 1.0, &mut noise).unwrap();
        assert_eq!(actor.log_std.as_tensor().to_vec1::<f32>().unwrap(), vec![-0.5, -0.5]);
        let obs = t(&[100.0, -50.0, 3.0, 0.0, 0.0, 0.0], 2, 3);
        for row in actor.mean(&obs).unwrap().to_vec2::<f32>().unwrap() {
            assert!(row.iter().all(|m| m.abs() <= 1.0));
        }
        // Samples spread around the mean with σ = e^−0.5.
        let zeros = t(&vec![0.0; 3 * 4000], 4000, 3);
        let mean0 = actor.mean(&t(&[0.0; 3], 1, 3)).unwrap().to_vec2::<f32>().unwrap()[0].clone();
        let samples = actor.sample(&zeros, &mut noise).unwrap();
        let var: f64 = samples
            .chunks(2)
            .map(|a| f64::from(a[0] - mean0[0]).powi(2))
            .sum::<f64>()
            / 4000.0;
        assert!((var.sqrt() - (-0.5f64).exp()).abs() < 0.03, "σ {}", var.sqrt());
    }
}
