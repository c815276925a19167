//! COptiDICE (OSRL `coptidice.py`, spec 5.8): offline constrained policy optimisation by stationary distribution
//! correction estimation.
//!
//! With the soft-χ² f-divergence (`f(x) = x(log(x + 1e-10) − 1) + 1` below 1, `½(x − 1)²` above;
//! `(f')⁻¹(x) = eˣ` below 0, `x + 1` above), α = 0.5 and `λ = softplus(λ_raw)`:
//! - `e(s, a, s') = r − λ·c + γ(1 − d)·ν(s') − ν(s)`, the optimal ratio `w = relu((f')⁻¹(e/α))`;
//! - χ, τ: an upper bound on the policy's cost — batch weights `softmax(ℓ/τ)·B` with
//!   `ℓ = (1 − γ)·χ(s)·init/p₀ + w·(c + γ(1 − d)·χ(s') − χ(s))`; χ minimises `mean(weights·ℓ)`, `τ = softplus(τ_raw)`
//!   minimises `τ·(ε − D_KL)` (ε = 0.01);
//! - ν minimises `(1 − γ)·mean(ν(s)·init/p₀) + mean(w·e − α·f(w))`;
//! - λ minimises `λ·(qc_thres − mean(weights·w·c))`;
//! - the policy is weighted behaviour cloning: `−mean(w·log N(a + ε_a | μ, σ)(s + ε_s))`, with w from the updated
//!   ν, ε drawn at 0.1 × the data's per-dimension standard deviation, and the pre-tanh Normal's density (OSRL's
//!   choice: no tanh correction).
//!
//! ν and χ are ensembles of 2 V-networks answering their minimum. Evaluation plays `tanh(μ)`.

use std::path::Path;

use dsrl_policy::adam::Adam;
use dsrl_policy::layers::{log_softmax, softmax};
use dsrl_policy::noise::Noise;
use dsrl_policy::offline::{Ensemble, qc_threshold, softplus};
use dsrl_policy::squashed::{SquashedGaussianActor, normal_log_prob};
use dsrl_policy::{Device, Tensor, Var};

use crate::Demonstrations;
use crate::offline::{Batch, Figures, ThresholdLearner, Transitions, normals, write_squashed_actor};

/// OSRL's COptiDICE configuration (spec 5.8; `examples/configs/coptidice_configs.py`).
#[derive(Debug, Clone, PartialEq)]
pub struct CoptidiceSettings {
    pub hidden_sizes: Vec<usize>,
    pub num_nu: usize,
    pub num_chi: usize,
    pub gamma: f64,
    pub alpha: f64,
    pub cost_ub_epsilon: f64,
    pub actor_lr: f64,
    pub critic_lr: f64,
    pub scalar_lr: f64,
    pub reward_scale: f64,
    pub cost_scale: f64,
    pub batch_size: usize,
    pub seed: u64,
}

impl Default for CoptidiceSettings {
    fn default() -> Self {
        CoptidiceSettings {
            hidden_sizes: vec![256, 256],
            num_nu: 2,
            num_chi: 2,
            gamma: 0.99,
            alpha: 0.5,
            cost_ub_epsilon: 0.01,
            actor_lr: 1e-4,
            critic_lr: 1e-4,
            scalar_lr: 1e-4,
            reward_scale: 0.1,
            cost_scale: 1.0,
            batch_size: 512,
            seed: 0,
        }
    }
}

/// The soft-χ² divergence's `f`, element-wise.
pub fn soft_chi_f(x: &Tensor) -> anyhow::Result<Tensor> {
    let below = x
        .mul(&x.affine(1.0, 1e-10)?.log()?.affine(1.0, -1.0)?)?
        .affine(1.0, 1.0)?;
    let above = x.affine(1.0, -1.0)?.sqr()?.affine(0.5, 0.0)?;
    Ok(x.lt(1.0)?.where_cond(&below, &above)?)
}

/// The soft-χ² divergence's `(f')⁻¹`, element-wise.
pub fn soft_chi_f_prime_inverse(x: &Tensor) -> anyhow::Result<Tensor> {
    let below = x.minimum(0.0)?.exp()?;
    let above = x.affine(1.0, 1.0)?;
    Ok(x.lt(0.0)?.where_cond(&below, &above)?)
}

pub struct CoptidiceLearner {
    pub settings: CoptidiceSettings,
    pub actor: SquashedGaussianActor,
    nu: Ensemble,
    chi: Ensemble,
    /// The unconstrained parameters behind τ and λ (both start at 1, so τ = λ = softplus(1) ≈ 1.31).
    tau: Var,
    lmbda: Var,
    actor_optim: Adam,
    nu_optim: Adam,
    chi_optim: Adam,
    tau_optim: Adam,
    lmbda_optim: Adam,
    qc_thres: f64,
    obs_std: Tensor,
    act_std: Tensor,
    noise: Noise,
    data: Transitions,
    obs_dim: usize,
}

impl CoptidiceLearner {
    /// A learner for the cost threshold `kappa` of a task whose episodes last `episode_len` steps, on the CPU.
    pub fn new(
        settings: CoptidiceSettings,
        data: &Demonstrations,
        kappa: f64,
        episode_len: usize,
    ) -> anyhow::Result<Self> {
        Self::on_device(settings, data, kappa, episode_len, &Device::Cpu)
    }

    /// As [`CoptidiceLearner::new`], training on `device` (networks initialised on the CPU from the seed, then
    /// moved).
    pub fn on_device(
        settings: CoptidiceSettings,
        data: &Demonstrations,
        kappa: f64,
        episode_len: usize,
        device: &Device,
    ) -> anyhow::Result<Self> {
        let o = data.obs_dim;
        let mut noise = Noise::seeded(settings.seed);
        let tau = Var::from_vec(vec![1.0f32], 1, device)?;
        let lmbda = Var::from_vec(vec![1.0f32], 1, device)?;
        let actor =
            SquashedGaussianActor::new(o, data.act_dim, &settings.hidden_sizes, &mut noise)?.to_device(device)?;
        let nu = Ensemble::new("nu", o, &settings.hidden_sizes, settings.num_nu, &mut noise)?.to_device(device)?;
        let chi = Ensemble::new("chi", o, &settings.hidden_sizes, settings.num_chi, &mut noise)?.to_device(device)?;
        let transitions = Transitions::new(data, device)?;
        let (obs_std, act_std) = transitions.stds()?;
        Ok(CoptidiceLearner {
            actor_optim: Adam::new(actor.named_vars(), settings.actor_lr, None)?,
            nu_optim: Adam::new(nu.named_vars(), settings.critic_lr, None)?,
            chi_optim: Adam::new(chi.named_vars(), settings.critic_lr, None)?,
            tau_optim: Adam::new(vec![("tau".into(), tau.clone())], settings.scalar_lr, None)?,
            lmbda_optim: Adam::new(vec![("lmbda".into(), lmbda.clone())], settings.scalar_lr, None)?,
            qc_thres: qc_threshold(kappa, settings.gamma, episode_len),
            tau,
            lmbda,
            obs_std,
            act_std,
            data: transitions,
            obs_dim: o,
            actor,
            nu,
            chi,
            noise,
            settings,
        })
    }

    /// `(ν(s), e, w)` for the batch with multiplier `lambda` (a number: no gradient flows into λ here).
    fn optimal_w(
        &self,
        obs: &Tensor,
        next_obs: &Tensor,
        reward: &Tensor,
        cost: &Tensor,
        done: &Tensor,
        lambda: f64,
    ) -> anyhow::Result<(Tensor, Tensor, Tensor)> {
        let gamma = self.settings.gamma;
        let nu_s = Ensemble::min(&self.nu.values(obs)?)?;
        let nu_next = Ensemble::min(&self.nu.values(next_obs)?)?;
        let e = reward
            .sub(&cost.affine(lambda, 0.0)?)?
            .add(&done.affine(-gamma, gamma)?.mul(&nu_next)?)?
            .sub(&nu_s)?;
        let w = soft_chi_f_prime_inverse(&e.affine(1.0 / self.settings.alpha, 0.0)?)?.relu()?;
        Ok((nu_s, e, w))
    }
}

fn scalar(t: &Tensor) -> anyhow::Result<f64> {
    Ok(f64::from(t.flatten_all()?.to_vec1::<f32>()?[0]))
}

impl ThresholdLearner for CoptidiceLearner {
    fn modules(&self) -> Vec<(&'static str, Vec<(String, Var)>)> {
        vec![
            ("actor", self.actor.named_vars()),
            ("nu_network", self.nu.named_vars()),
            ("chi_network", self.chi.named_vars()),
            ("tau", vec![("tau".into(), self.tau.clone())]),
            ("lmbda", vec![("lmbda".into(), self.lmbda.clone())]),
        ]
    }

    fn optimizers(&mut self) -> Vec<(&'static str, &mut Adam)> {
        vec![
            ("actor_optim", &mut self.actor_optim),
            ("nu_optim", &mut self.nu_optim),
            ("chi_optim", &mut self.chi_optim),
            ("tau_optim", &mut self.tau_optim),
            ("lmbda_optim", &mut self.lmbda_optim),
        ]
    }

    fn noise(&mut self) -> &mut Noise {
        &mut self.noise
    }

    fn sample(&mut self) -> anyhow::Result<Batch> {
        let s = &self.settings;
        self.data
            .sample(s.batch_size, s.reward_scale, s.cost_scale, &mut self.noise)
    }

    fn update(&mut self, batch: &Batch) -> anyhow::Result<Figures> {
        let s = self.settings.clone();
        let b = batch.obs.dim(0)?;
        let (gamma, p0) = (s.gamma, self.data.init_proportion);

        // 1. The optimal distribution ratio.
        let lambda = softplus(self.lmbda.as_tensor())?;
        let lambda_now = scalar(&lambda)?;
        let (nu_s, e, w) = self.optimal_w(
            &batch.obs,
            &batch.next_obs,
            &batch.reward,
            &batch.cost,
            &batch.done,
            lambda_now,
        )?;
        let nu_init = nu_s.mul(&batch.is_init)?.affine(1.0 / p0, 0.0)?;
        let w_fixed = w.detach();
        let divergence = scalar(&soft_chi_f(&w_fixed)?.mean_all()?)?;

        // 1.1 χ and τ: the cost upper bound.
        let tau = softplus(self.tau.as_tensor())?;
        let tau_now = scalar(&tau)?;
        let chi_s = Ensemble::min(&self.chi.values(&batch.obs)?)?;
        let chi_next = Ensemble::min(&self.chi.values(&batch.next_obs)?)?;
        let chi_init = chi_s.mul(&batch.is_init)?.affine(1.0 / p0, 0.0)?;
        let ell = chi_init.affine(1.0 - gamma, 0.0)?.add(
            &w_fixed.mul(
                &batch
                    .cost
                    .add(&batch.done.affine(-gamma, gamma)?.mul(&chi_next)?)?
                    .sub(&chi_s)?,
            )?,
        )?;
        let logits = ell.affine(1.0 / tau_now, 0.0)?;
        let weights = softmax(&logits, 0)?.affine(b as f64, 0.0)?;
        let log_weights = log_softmax(&logits, 0)?.affine(1.0, (b as f64).ln())?;
        let kl = weights.mul(&log_weights)?.sub(&weights)?.affine(1.0, 1.0)?.mean_all()?;
        let kl_now = scalar(&kl)?;
        let weighted_cost = scalar(&weights.mul(&w_fixed)?.mul(&batch.cost)?.mean_all()?)?;
        let chi_loss = weights.mul(&ell)?.mean_all()?;
        self.chi_optim.step(&chi_loss.backward()?)?;
        let tau_loss = tau.affine(s.cost_ub_epsilon - kl_now, 0.0)?.sum_all()?;
        self.tau_optim.step(&tau_loss.backward()?)?;

        // 1.2 ν.
        let nu_loss = nu_init
            .mean_all()?
            .affine(1.0 - gamma, 0.0)?
            .add(&w.mul(&e)?.sub(&soft_chi_f(&w)?.affine(s.alpha, 0.0)?)?.mean_all()?)?;
        let td_error = scalar(&e.sqr()?.mean_all()?)?;
        self.nu_optim.step(&nu_loss.backward()?)?;

        // 1.3 λ.
        let lambda_loss = lambda.affine(self.qc_thres - weighted_cost, 0.0)?.sum_all()?;
        self.lmbda_optim.step(&lambda_loss.backward()?)?;

        // 2. Policy extraction: weighted behaviour cloning on noised inputs, w from the updated ν.
        let obs_eps = normals(&mut self.noise, b, self.obs_dim, self.data.device())?
            .broadcast_mul(&self.obs_std)?
            .affine(0.1, 0.0)?;
        let act_eps = normals(&mut self.noise, b, self.actor.act_dim, self.data.device())?
            .broadcast_mul(&self.act_std)?
            .affine(0.1, 0.0)?;
        let (mean, log_std) = self.actor.distribution(&batch.obs.add(&obs_eps)?)?;
        let (_, _, w) = self.optimal_w(
            &batch.obs,
            &batch.next_obs,
            &batch.reward,
            &batch.cost,
            &batch.done,
            lambda_now,
        )?;
        let log_prob = normal_log_prob(&batch.act.add(&act_eps)?, &mean, &log_std)?;
        let actor_loss = w.detach().mul(&log_prob)?.mean_all()?.neg()?;
        self.actor_optim.step(&actor_loss.backward()?)?;

        Ok(vec![
            ("nu", scalar(&nu_loss)?),
            ("chi", scalar(&chi_loss)?),
            ("actor", scalar(&actor_loss)?),
            ("td_error", td_error),
            ("d_kl", kl_now),
            ("d_f", divergence),
            ("weighted_cost", weighted_cost),
            ("tau", tau_now),
            ("lagrangian", lambda_now),
        ])
    }

    fn batch_size(&self) -> usize {
        self.settings.batch_size
    }

    fn qc_threshold(&self) -> f64 {
        self.qc_thres
    }

    fn settings(&self) -> String {
        format!("{:?}", self.settings)
    }

    fn write(&self, dir: &Path, task: &str, kappa: f64, training: serde_json::Value) -> anyhow::Result<()> {
        write_squashed_actor(
            &self.actor,
            &self.settings.hidden_sizes,
            dir,
            task,
            self.obs_dim,
            kappa,
            training,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::offline::tests::{figure, first_weights, plays_as_written, run, toy};

    #[test]
    fn the_soft_chi_functions_are_the_spec_by_hand() {
        let x = Tensor::new(&[-2.0f32, 0.0, 0.5, 1.0, 3.0], &Device::Cpu).unwrap();
        let inv: Vec<f32> = soft_chi_f_prime_inverse(&x).unwrap().to_vec1().unwrap();
        let want = [(-2.0f32).exp(), 1.0, 1.5, 2.0, 4.0];
        for (a, b) in inv.iter().zip(&want) {
            assert!((a - b).abs() < 1e-6, "{inv:?}");
        }
        let w = Tensor::new(&[0.0f32, 0.5, 1.0, 3.0], &Device::Cpu).unwrap();
        let f: Vec<f32> = soft_chi_f(&w).unwrap().to_vec1().unwrap();
        let want = [1.0f32, 0.5 * (0.5f32.ln() - 1.0) + 1.0, 0.0, 2.0];
        for (a, b) in f.iter().zip(&want) {
            assert!((a - b).abs() < 1e-5, "{f:?}");
        }
        // f is continuous with a continuous derivative at 1 (both pieces: value 0, slope 0).
        let near = Tensor::new(&[0.999f32, 1.001], &Device::Cpu).unwrap();
        let v: Vec<f32> = soft_chi_f(&near).unwrap().to_vec1().unwrap();
        assert!(v.iter().all(|x| x.abs() < 1e-5), "{v:?}");
    }

    #[test]
    fn a_few_steps_train_every_part_deterministically_and_write_what_the_evaluator_plays() {
        let data = toy();
        let settings = |seed| CoptidiceSettings {
            hidden_sizes: vec![16, 16],
            batch_size: 32,
            seed,
            ..CoptidiceSettings::default()
        };
        // λ follows the cost bound: with κ = 0.02 (a per-step threshold of ~0.019) the weighted cost is over it
        // and λ rises; with κ = 2 (~1.9) it is under it and λ falls.
        let mut strict = CoptidiceLearner::new(settings(3), &data, 0.02, 10).unwrap();
        let (first, last) = run(&mut strict, 60);
        assert!(
            (figure(&first, "tau") - (1.0 + 1f64.exp()).ln()).abs() < 1e-6,
            "{first:?}"
        );
        assert!(figure(&first, "weighted_cost") > strict.qc_threshold(), "{first:?}");
        assert!(
            figure(&last, "lagrangian") > figure(&first, "lagrangian"),
            "{first:?} -> {last:?}"
        );
        assert!(figure(&last, "d_kl") >= 0.0);
        let mut learner = CoptidiceLearner::new(settings(3), &data, 2.0, 10).unwrap();
        let (first, last) = run(&mut learner, 60);
        assert!(figure(&first, "weighted_cost") < learner.qc_threshold(), "{first:?}");
        assert!(
            figure(&last, "lagrangian") < figure(&first, "lagrangian"),
            "{first:?} -> {last:?}"
        );

        let mut again = CoptidiceLearner::new(settings(3), &data, 2.0, 10).unwrap();
        run(&mut again, 60);
        assert_eq!(
            first_weights(learner.actor.named_vars()),
            first_weights(again.actor.named_vars())
        );

        let obs = [0.3f32, 0.7];
        let o = Tensor::from_vec(obs.to_vec(), (1, 2), &Device::Cpu).unwrap();
        let mine: Vec<f32> = learner
            .actor
            .deterministic(&o)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        plays_as_written(&learner, obs, mine[0]);
    }
}
