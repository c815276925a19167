//! BEAR-Lag (OSRL `bearl.py`, spec 5.7): bootstrapping error accumulation reduction with a PID Lagrangian.
//!
//! A squashed Gaussian actor kept near the data's actions by an MMD constraint against a VAE of those actions,
//! double-ensemble reward and cost critics (2 + 2 networks each) with target copies, and OSRL's PID controller on
//! the cost value:
//! - targets: each next state repeated 10×, actions drawn from the target actor; per draw
//!   `0.75·min(q1, q2) + 0.25·max(q1, q2)`, the maximum over the draws; `y = r + γ(1 − d)·q`, and `y_c = c + γ·q_c`
//!   (OSRL's cost target has no (1 − d));
//! - actor: MMD (Gaussian kernel, σ = 50) between 10 raw (pre-tanh) VAE decodes and 10 pre-tanh actor draws per
//!   state; `L = mean(−min(q1, q2)(s, a₀) + α·(MMD − 0.05)) + mean((Qc(s, a₀) − qc_thres)·λ)`, λ from the PID;
//!   then `log α += lr_α·α·mean(MMD − 0.05)`, clamped to [−5, 5].
//!
//! One step, in OSRL's order: VAE → reward critic → cost critic → actor → soft updates (τ = 0.005) of both critics
//! and the target actor. Evaluation plays `tanh(μ)`.

use std::path::Path;

use dsrl_policy::adam::Adam;
use dsrl_policy::noise::Noise;
use dsrl_policy::offline::{DoubleCritic, PidLagrangian, concat, qc_threshold, repeat_rows, soft_update};
use dsrl_policy::squashed::SquashedGaussianActor;
use dsrl_policy::vae::Vae;
use dsrl_policy::{Device, Tensor, Var};

use crate::offline::{Batch, Figures, ThresholdLearner, Transitions, normals, write_squashed_actor};
use crate::{Demonstrations, MAX_ACTION};

/// OSRL's BEAR-L configuration (spec 5.7; `examples/configs/bearl_configs.py` and the trainer's defaults).
#[derive(Debug, Clone, PartialEq)]
pub struct BearlSettings {
    pub hidden_sizes: Vec<usize>,
    pub vae_hidden: usize,
    pub num_q: usize,
    pub gamma: f64,
    pub tau: f64,
    pub beta: f64,
    /// Weight of the smaller of the two ensembles' values in the target.
    pub lmbda: f64,
    pub mmd_sigma: f64,
    pub target_mmd_thresh: f64,
    pub num_samples_mmd_match: usize,
    pub sample_action_num: usize,
    /// Steps during which only the MMD term trains the actor (OSRL's configs: 0).
    pub start_update_policy_step: u64,
    pub lr: f64,
    pub alpha_lr: f64,
    pub pid: (f64, f64, f64),
    pub reward_scale: f64,
    pub cost_scale: f64,
    pub batch_size: usize,
    pub seed: u64,
}

impl Default for BearlSettings {
    fn default() -> Self {
        BearlSettings {
            hidden_sizes: vec![256, 256],
            vae_hidden: 400,
            num_q: 2,
            gamma: 0.99,
            tau: 0.005,
            beta: 0.5,
            lmbda: 0.75,
            mmd_sigma: 50.0,
            target_mmd_thresh: 0.05,
            num_samples_mmd_match: 10,
            sample_action_num: 10,
            start_update_policy_step: 0,
            lr: 1e-3,
            alpha_lr: 1e-3,
            pid: (0.1, 0.003, 0.001),
            reward_scale: 0.1,
            cost_scale: 1.0,
            batch_size: 512,
            seed: 0,
        }
    }
}

pub struct BearlLearner {
    pub settings: BearlSettings,
    pub actor: SquashedGaussianActor,
    actor_target: SquashedGaussianActor,
    pub vae: Vae,
    critic: DoubleCritic,
    critic_target: DoubleCritic,
    cost_critic: DoubleCritic,
    cost_critic_target: DoubleCritic,
    actor_optim: Adam,
    critic_optim: Adam,
    cost_critic_optim: Adam,
    vae_optim: Adam,
    pub log_alpha: f64,
    pid: PidLagrangian,
    steps: u64,
    noise: Noise,
    data: Transitions,
    obs_dim: usize,
}

/// OSRL's Gaussian-kernel MMD between two sets of `n` samples per state, `x` and `y` `[states, n, dim]`:
/// `sqrt(k(x, x) + k(y, y) − 2·k(x, y) + 1e-6)` with `k` the mean over sample pairs of
/// `exp(−‖a − b‖² / (2σ))`. Returns `[states]`.
pub fn mmd_gaussian(x: &Tensor, y: &Tensor, sigma: f64) -> anyhow::Result<Tensor> {
    let kernel = |a: &Tensor, b: &Tensor| -> anyhow::Result<Tensor> {
        let diff = a.unsqueeze(2)?.broadcast_sub(&b.unsqueeze(1)?)?;
        Ok(diff
            .sqr()?
            .sum(3)?
            .affine(-1.0 / (2.0 * sigma), 0.0)?
            .exp()?
            .mean(2)?
            .mean(1)?)
    };
    let (xx, yy, xy) = (kernel(x, x)?, kernel(y, y)?, kernel(x, y)?);
    Ok(xx.add(&yy)?.sub(&xy.affine(2.0, 0.0)?)?.affine(1.0, 1e-6)?.sqrt()?)
}

impl BearlLearner {
    /// A learner for the cost threshold `kappa` of a task whose episodes last `episode_len` steps.
    pub fn new(settings: BearlSettings, data: &Demonstrations, kappa: f64, episode_len: usize) -> anyhow::Result<Self> {
        Self::on_device(settings, data, kappa, episode_len, &Device::Cpu)
    }

    /// As [`BearlLearner::new`], training on `device` (networks initialised on the CPU from the seed, then moved).
    pub fn on_device(
        settings: BearlSettings,
        data: &Demonstrations,
        kappa: f64,
        episode_len: usize,
        device: &Device,
    ) -> anyhow::Result<Self> {
        let (o, a) = (data.obs_dim, data.act_dim);
        let mut noise = Noise::seeded(settings.seed);
        let actor = SquashedGaussianActor::new(o, a, &settings.hidden_sizes, &mut noise)?.to_device(device)?;
        let critic = DoubleCritic::new("critic", o + a, &settings.hidden_sizes, settings.num_q, &mut noise)?
            .to_device(device)?;
        let cost_critic = DoubleCritic::new("cost_critic", o + a, &settings.hidden_sizes, settings.num_q, &mut noise)?
            .to_device(device)?;
        let vae = Vae::new(o, a, settings.vae_hidden, 2 * a, MAX_ACTION, &mut noise)?.to_device(device)?;
        let (kp, ki, kd) = settings.pid;
        Ok(BearlLearner {
            actor_optim: Adam::new(actor.named_vars(), settings.lr, None)?,
            critic_optim: Adam::new(critic.named_vars(), settings.lr, None)?,
            cost_critic_optim: Adam::new(cost_critic.named_vars(), settings.lr, None)?,
            vae_optim: Adam::new(vae.named_vars(), settings.lr, None)?,
            actor_target: actor.copy()?,
            critic_target: critic.copy()?,
            cost_critic_target: cost_critic.copy()?,
            log_alpha: 0.0,
            pid: PidLagrangian::new(kp, ki, kd, qc_threshold(kappa, settings.gamma, episode_len)),
            steps: 0,
            data: Transitions::new(data, device)?,
            obs_dim: o,
            actor,
            vae,
            critic,
            cost_critic,
            noise,
            settings,
        })
    }

    /// The target of a critic from `target`: `reward + discount·q` over repeated next states with target-actor
    /// draws (`discount` carries OSRL's `(1 − d)` for the reward and not for the cost).
    fn backup(&mut self, next_obs: &Tensor, reward: &Tensor, discount: &Tensor, cost: bool) -> anyhow::Result<Tensor> {
        let n = self.settings.sample_action_num;
        let next_rep = repeat_rows(next_obs, n)?;
        let next_act = self
            .actor_target
            .sample_with(&next_rep, &mut self.noise)?
            .action
            .detach();
        let target = if cost {
            &self.cost_critic_target
        } else {
            &self.critic_target
        };
        let (_, q1, q2) = target.predict(&concat(&next_rep, &next_act)?)?;
        let q = DoubleCritic::soft_clipped_max(&q1, &q2, self.settings.lmbda, n)?;
        Ok(reward.add(&discount.mul(&q)?)?.detach())
    }
}

impl ThresholdLearner for BearlLearner {
    fn modules(&self) -> Vec<(&'static str, Vec<(String, Var)>)> {
        vec![
            ("actor", self.actor.named_vars()),
            ("critic", self.critic.named_vars()),
            ("cost_critic", self.cost_critic.named_vars()),
            ("vae", self.vae.named_vars()),
            ("actor_old", self.actor_target.named_vars()),
            ("critic_old", self.critic_target.named_vars()),
            ("cost_critic_old", self.cost_critic_target.named_vars()),
        ]
    }

    fn optimizers(&mut self) -> Vec<(&'static str, &mut Adam)> {
        vec![
            ("actor_optim", &mut self.actor_optim),
            ("critic_optim", &mut self.critic_optim),
            ("cost_critic_optim", &mut self.cost_critic_optim),
            ("vae_optim", &mut self.vae_optim),
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
        let input = concat(&batch.obs, &batch.act)?;

        // VAE.
        let eps = normals(&mut self.noise, b, self.vae.latent_dim, self.data.device())?;
        let out = self.vae.forward(&batch.obs, &batch.act, &eps)?;
        let (vae_loss, _, _) = Vae::loss(&out, &batch.act, s.beta)?;
        self.vae_optim.step(&vae_loss.backward()?)?;

        // Critics.
        let discount = batch.done.affine(-s.gamma, s.gamma)?;
        let target = self.backup(&batch.next_obs, &batch.reward, &discount, false)?;
        let (values, _, _) = self.critic.predict(&input)?;
        let critic_loss = dsrl_policy::offline::Ensemble::loss(&values, &target)?;
        self.critic_optim.step(&critic_loss.backward()?)?;
        let discount = Tensor::full(s.gamma as f32, b, self.data.device())?;
        let target = self.backup(&batch.next_obs, &batch.cost, &discount, true)?;
        let (values, _, _) = self.cost_critic.predict(&input)?;
        let cost_critic_loss = dsrl_policy::offline::Ensemble::loss(&values, &target)?;
        self.cost_critic_optim.step(&cost_critic_loss.backward()?)?;

        // Actor: MMD to the VAE's raw decodes, reward value, and the PID-weighted cost value.
        let n = s.num_samples_mmd_match;
        let (o, a) = (self.obs_dim, self.actor.act_dim);
        let stacked = repeat_rows(&batch.obs, n)?;
        let z = normals(&mut self.noise, b * n, self.vae.latent_dim, self.data.device())?.clamp(-0.5, 0.5)?;
        let vae_raw = self
            .vae
            .decoder
            .forward(&Tensor::cat(&[&stacked, &z], 1)?)?
            .detach()
            .reshape((b, n, a))?;
        let draws = self.actor.sample_with(&stacked, &mut self.noise)?;
        let mmd = mmd_gaussian(&vae_raw, &draws.pre_tanh.reshape((b, n, a))?, s.mmd_sigma)?;
        let first: Vec<u32> = (0..b as u32).map(|i| i * n as u32).collect();
        let a0 = draws
            .action
            .index_select(&Tensor::from_vec(first, b, self.data.device())?, 0)?;
        let policy_input = concat(&batch.obs, &a0)?;
        debug_assert_eq!(policy_input.dims(), &[b, o + a]);
        let (_, q1, q2) = self.critic.predict(&policy_input)?;
        let (_, qc1, qc2) = self.cost_critic.predict(&policy_input)?;
        let qc = qc1.minimum(&qc2)?;
        let lagrangian = self.pid.control(&qc.detach().to_vec1::<f32>()?);
        let alpha = self.log_alpha.exp();
        let mmd_term = mmd.affine(alpha, -alpha * s.target_mmd_thresh)?;
        let per_state = if self.steps >= s.start_update_policy_step {
            mmd_term.sub(&q1.minimum(&q2)?)?
        } else {
            mmd_term
        };
        let penalty = qc.affine(lagrangian, -lagrangian * self.pid.threshold)?.mean_all()?;
        let actor_loss = per_state.mean_all()?.add(&penalty)?;
        self.actor_optim.step(&actor_loss.backward()?)?;
        let mmd_mean = f64::from(mmd.mean_all()?.to_scalar::<f32>()?);
        self.log_alpha = (self.log_alpha + s.alpha_lr * alpha * (mmd_mean - s.target_mmd_thresh)).clamp(-5.0, 5.0);
        self.steps += 1;

        soft_update(&self.critic_target.named_vars(), &self.critic.named_vars(), s.tau)?;
        soft_update(
            &self.cost_critic_target.named_vars(),
            &self.cost_critic.named_vars(),
            s.tau,
        )?;
        soft_update(&self.actor_target.named_vars(), &self.actor.named_vars(), s.tau)?;
        Ok(vec![
            ("vae", f64::from(vae_loss.to_scalar::<f32>()?)),
            ("critic", f64::from(critic_loss.to_scalar::<f32>()?)),
            ("cost_critic", f64::from(cost_critic_loss.to_scalar::<f32>()?)),
            ("actor", f64::from(actor_loss.to_scalar::<f32>()?)),
            ("mmd", mmd_mean),
            ("alpha", self.log_alpha.exp()),
            ("lagrangian", lagrangian),
        ])
    }

    fn batch_size(&self) -> usize {
        self.settings.batch_size
    }

    fn qc_threshold(&self) -> f64 {
        self.pid.threshold
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

    fn small(seed: u64) -> BearlSettings {
        BearlSettings {
            hidden_sizes: vec![16, 16],
            vae_hidden: 16,
            batch_size: 32,
            seed,
            ..BearlSettings::default()
        }
    }

    #[test]
    fn the_mmd_is_osrls_formula_by_hand() {
        // One state, two samples of one dimension each: x = (0, 1), y = (0, 3), σ = 0.5 so 2σ = 1.
        let x = Tensor::new(&[[[0.0f32], [1.0]]], &Device::Cpu).unwrap();
        let y = Tensor::new(&[[[0.0f32], [3.0]]], &Device::Cpu).unwrap();
        let got = mmd_gaussian(&x, &y, 0.5).unwrap().to_vec1::<f32>().unwrap()[0];
        let k = |d: f64| (-d * d).exp();
        let xx = (2.0 * k(0.0) + 2.0 * k(1.0)) / 4.0;
        let yy = (2.0 * k(0.0) + 2.0 * k(3.0)) / 4.0;
        let xy = (k(0.0) + k(3.0) + k(1.0) + k(2.0)) / 4.0;
        let want = (xx + yy - 2.0 * xy + 1e-6).sqrt();
        assert!((f64::from(got) - want).abs() < 1e-6, "{got} vs {want}");
        // Identical sets: only the 1e-6 floor is left.
        let same = mmd_gaussian(&x, &x, 0.5).unwrap().to_vec1::<f32>().unwrap()[0];
        assert!((f64::from(same) - 1e-3).abs() < 1e-4, "{same}");
    }

    #[test]
    fn a_few_steps_train_every_part_deterministically_and_write_what_the_evaluator_plays() {
        let data = toy();
        // κ = 0.02 over 10 steps: a per-step threshold of ~0.019, which half the data (cost 1 per step) breaks.
        let mut learner = BearlLearner::new(small(3), &data, 0.02, 10).unwrap();
        let (first, last) = run(&mut learner, 60);
        assert!(figure(&last, "vae") < figure(&first, "vae"), "{first:?} -> {last:?}");
        // The cost values learned from that data pass the threshold: λ rises.
        assert!(figure(&last, "lagrangian") > 0.0, "{last:?}");
        assert!(figure(&last, "mmd") > 0.0);

        let mut again = BearlLearner::new(small(3), &data, 0.02, 10).unwrap();
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
