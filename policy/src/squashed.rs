//! OSRL's `SquashedGaussianMLPActor` (spec 5.3) as BEAR-L, CPQ and COptiDICE train it:
//!
//! ```text
//! h = relu(trunk(obs))                      trunk [obs, hidden..], ReLU after every layer
//! μ = mu(h),  log σ = clamp(log_std(h), −20, 2)
//! u = μ + σ·ε   (ε ~ N(0, 1); u = μ when deterministic)
//! action = tanh(u),  log π = Σ log N(u; μ, σ) − Σ 2·(ln 2 − u − softplus(−2u))
//! ```
//!
//! Tensors `actor.trunk.<i>`, `actor.mu.0`, `actor.log_std.0`: what the evaluator's `squashed_gaussian_mlp`
//! reads (it plays `max_action · tanh(μ)` and ignores `actor.log_std`, which only training uses).

use candle_core::{Tensor, Var};

use crate::Result;
use crate::mlp::{Activation, Mlp};
use crate::noise::Noise;
use crate::offline::softplus;

/// OSRL's clamp of the actor's log σ.
pub const LOG_STD_RANGE: (f64, f64) = (-20.0, 2.0);

pub struct SquashedGaussianActor {
    pub trunk: Mlp,
    pub mu: Mlp,
    pub log_std: Mlp,
    pub act_dim: usize,
}

/// One reparameterised draw for a batch: the pre-squash sample `u` (BEAR-L's MMD and CPQ's OOD samples use it),
/// `tanh(u)` and the log-probability of the squashed action.
pub struct SquashedSample {
    pub pre_tanh: Tensor,
    pub action: Tensor,
    pub log_prob: Tensor,
}

impl SquashedGaussianActor {
    /// PyTorch-default initialised layers, as OSRL leaves them.
    pub fn new(obs_dim: usize, act_dim: usize, hidden: &[usize], noise: &mut Noise) -> Result<Self> {
        assert!(!hidden.is_empty(), "the squashed Gaussian actor needs a hidden layer");
        let mut trunk_sizes = vec![obs_dim];
        trunk_sizes.extend(hidden);
        let last = *hidden.last().expect("checked");
        Ok(SquashedGaussianActor {
            trunk: Mlp::pytorch_default("actor.trunk", &trunk_sizes, Activation::Relu, noise)?,
            mu: Mlp::pytorch_default("actor.mu", &[last, act_dim], Activation::Relu, noise)?,
            log_std: Mlp::pytorch_default("actor.log_std", &[last, act_dim], Activation::Relu, noise)?,
            act_dim,
        })
    }

    /// The pre-squash Normal's parameters for `[batch, obs]` rows: (μ, clamped log σ), each `[batch, act]`.
    pub fn distribution(&self, obs: &Tensor) -> Result<(Tensor, Tensor)> {
        // The trunk's ReLU also follows its last layer (`mlp(..., activation, activation)`).
        let h = crate::fused::relu(&self.trunk.forward(obs)?)?;
        let mean = self.mu.forward(&h)?;
        let log_std = self.log_std.forward(&h)?.clamp(LOG_STD_RANGE.0, LOG_STD_RANGE.1)?;
        Ok((mean, log_std))
    }

    /// A reparameterised sample with the given standard normal draws `epsilon` (`[batch, act]`), differentiable in
    /// the actor's weights (`rsample`).
    pub fn sample(&self, obs: &Tensor, epsilon: &Tensor) -> Result<SquashedSample> {
        let (mean, log_std) = self.distribution(obs)?;
        let pre_tanh = mean.add(&log_std.exp()?.mul(epsilon)?)?;
        let log_prob = squashed_log_prob(&pre_tanh, &mean, &log_std)?;
        Ok(SquashedSample {
            action: pre_tanh.tanh()?,
            pre_tanh,
            log_prob,
        })
    }

    /// A sample drawn from `noise` (row-major `[batch, act]` standard normals).
    pub fn sample_with(&self, obs: &Tensor, noise: &mut Noise) -> Result<SquashedSample> {
        let rows = obs.dim(0)?;
        let epsilon = Tensor::from_vec(
            noise.normals_f32(rows * self.act_dim),
            (rows, self.act_dim),
            obs.device(),
        )?;
        self.sample(obs, &epsilon)
    }

    /// `tanh(μ)`: the deterministic action the evaluator plays (before `max_action`).
    pub fn deterministic(&self, obs: &Tensor) -> Result<Tensor> {
        Ok(self.distribution(obs)?.0.tanh()?)
    }

    pub fn named_vars(&self) -> Vec<(String, Var)> {
        [&self.trunk, &self.mu, &self.log_std]
            .into_iter()
            .flat_map(Mlp::named_vars)
            .collect()
    }

    /// A copy with the same weights and its own variables (a target network).
    pub fn copy(&self) -> Result<Self> {
        Ok(SquashedGaussianActor {
            trunk: self.trunk.copy()?,
            mu: self.mu.copy()?,
            log_std: self.log_std.copy()?,
            act_dim: self.act_dim,
        })
    }

    pub fn to_device(self, device: &candle_core::Device) -> Result<SquashedGaussianActor> {
        Ok(SquashedGaussianActor {
            trunk: self.trunk.to_device(device)?,
            mu: self.mu.to_device(device)?,
            log_std: self.log_std.to_device(device)?,
            ..self
        })
    }
}

/// The log-density of `tanh(u)` for `u ~ N(μ, σ)` with a per-row log σ (`[batch, act]`, as the actor's heads give
/// it): `log N(u) − Σ 2·(ln 2 − u − softplus(−2u))`, OSRL's numerically stable form of `log(1 − tanh²u)`.
fn squashed_log_prob(u: &Tensor, mean: &Tensor, log_std: &Tensor) -> Result<Tensor> {
    let log_jacobian = u
        .neg()?
        .sub(&softplus(&u.affine(-2.0, 0.0)?)?)?
        .affine(2.0, 2.0 * std::f64::consts::LN_2)?
        .sum(candle_core::D::Minus1)?;
    Ok(normal_log_prob(u, mean, log_std)?.sub(&log_jacobian)?)
}

/// Σ_d log N(x_d; μ_d, σ_d) per row, with per-row `log_std` (`[batch, act]`): the log-density of the pre-squash
/// Normal that COptiDICE's weighted behaviour cloning maximises (no tanh correction, as OSRL).
pub fn normal_log_prob(x: &Tensor, mean: &Tensor, log_std: &Tensor) -> Result<Tensor> {
    let z = x.sub(mean)?.div(&log_std.exp()?)?;
    Ok(z.sqr()?
        .affine(-0.5, -0.918_938_533_204_672_7)?
        .sub(log_std)?
        .sum(candle_core::D::Minus1)?)
}

#[cfg(test)]
mod tests {
    use candle_core::Device;

    use super::*;
    use crate::gaussian::gaussian_log_prob;

    fn t(values: &[f32], rows: usize, cols: usize) -> Tensor {
        Tensor::from_slice(values, (rows, cols), &Device::Cpu).unwrap()
    }

    #[test]
    fn a_sample_is_tanh_of_mean_plus_sigma_epsilon_with_the_squashed_density() {
        let mut noise = Noise::seeded(3);
        let actor = SquashedGaussianActor::new(3, 2, &[8, 8], &mut noise).unwrap();
        let obs = t(&[0.1, -0.4, 2.0, 1.0, 0.0, -1.0], 2, 3);
        let eps = t(&[0.3, -1.2, 0.0, 0.7], 2, 2);
        let s = actor.sample(&obs, &eps).unwrap();
        let (mean, log_std) = actor.distribution(&obs).unwrap();
        let (m, ls): (Vec<Vec<f32>>, Vec<Vec<f32>>) = (mean.to_vec2().unwrap(), log_std.to_vec2().unwrap());
        let u: Vec<Vec<f32>> = s.pre_tanh.to_vec2().unwrap();
        let a: Vec<Vec<f32>> = s.action.to_vec2().unwrap();
        let lp: Vec<f32> = s.log_prob.to_vec1().unwrap();
        let e = [[0.3f32, -1.2], [0.0, 0.7]];
        for r in 0..2 {
            let mut want = 0.0f64;
            for d in 0..2 {
                let ui = m[r][d] + ls[r][d].exp() * e[r][d];
                assert!((u[r][d] - ui).abs() < 1e-6);
                assert!((a[r][d] - ui.tanh()).abs() < 1e-6);
                let (ui, mi, si) = (f64::from(ui), f64::from(m[r][d]), f64::from(ls[r][d]).exp());
                want += -0.5 * ((ui - mi) / si).powi(2)
                    - si.ln()
                    - 0.5 * (2.0 * std::f64::consts::PI).ln()
                    - (1.0 - ui.tanh().powi(2)).ln();
            }
            assert!((f64::from(lp[r]) - want).abs() < 1e-4, "row {r}: {} vs {want}", lp[r]);
        }
        // With one shared σ the per-row density equals the shared helper's.
        let shared = gaussian_log_prob(&s.pre_tanh, &mean, &Tensor::new(&[0.0f32, 0.0], &Device::Cpu).unwrap())
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let rows = normal_log_prob(&s.pre_tanh, &mean, &mean.zeros_like().unwrap())
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert_eq!(shared.len(), rows.len());
        for (a, b) in shared.iter().zip(&rows) {
            assert!((a - b).abs() < 1e-5);
        }
    }

    #[test]
    fn the_log_std_is_clamped_and_the_deterministic_action_is_tanh_of_the_mean() {
        let mut noise = Noise::seeded(9);
        let actor = SquashedGaussianActor::new(2, 1, &[4], &mut noise).unwrap();
        // Huge weights on the log-std head push it past both ends of [−20, 2].
        let (_, w) = &actor.log_std.named_vars()[0];
        w.set(&Tensor::new(&[[1000.0f32, 0.0, 0.0, 0.0]], &Device::Cpu).unwrap())
            .unwrap();
        let obs = t(&[5.0, 5.0, -5.0, -5.0], 2, 2);
        let (mean, log_std) = actor.distribution(&obs).unwrap();
        for v in log_std.flatten_all().unwrap().to_vec1::<f32>().unwrap() {
            assert!((-20.0..=2.0).contains(&v), "{v}");
        }
        let det: Vec<f32> = actor
            .deterministic(&obs)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let m: Vec<f32> = mean.flatten_all().unwrap().to_vec1().unwrap();
        assert!(det.iter().zip(&m).all(|(d, m)| (d - m.tanh()).abs() < 1e-6));
    }
}
