//! CPQ (OSRL `cpq.py`, spec 5.8): Constraints Penalized Q-learning.
//!
//! A squashed Gaussian actor, reward and cost critics (ensembles of 2, each answering its minimum) with target
//! copies, and a VAE of the data's actions that flags out-of-distribution actions. With `q_thres` the per-step
//! cost threshold (`κ·(1 − γ^L)/(1 − γ)/L`):
//! - reward critic: `y = r + γ(1 − d)·1[Qc'(s', a') ≤ q_thres]·Q'(s', a')`, `a' ~ π(s')` — no reward flows
//!   through states whose cost value breaks the threshold;
//! - cost critic: `y_c = c + γ·Qc'(s', a')`. OSRL also computes a penalty on the cost of OOD actions (10 pre-tanh
//!   draws per state whose VAE KL is in the top quarter), weighted by `α = e^{log α}`; it is computed without a
//!   gradient, so it only shifts the reported loss, and `log α += lr_α·α·(qc_thres − mean(Qc_ood))`, clamped to
//!   [−5, 5], with `qc_thres = 1.5·q_thres`. Both are kept as OSRL has them;
//! - actor: `−mean(1[Qc(s, π) ≤ q_thres]·Q(s, π))`.
//!
//! One step, in OSRL's order: VAE → reward critic → cost critic → actor → soft updates (τ = 0.005).

use std::path::Path;

use dsrl_policy::adam::Adam;
use dsrl_policy::noise::Noise;
use dsrl_policy::offline::{Ensemble, concat, qc_threshold, quantile, soft_update};
use dsrl_policy::squashed::SquashedGaussianActor;
use dsrl_policy::vae::Vae;
use dsrl_policy::{DType, Tensor, Var};

use crate::offline::{Batch, Figures, ThresholdLearner, Transitions, normals, write_squashed_actor};
use crate::{Demonstrations, MAX_ACTION};

/// OSRL's CPQ configuration (spec 5.8; `examples/configs/cpq_configs.py`).
#[derive(Debug, Clone, PartialEq)]
pub struct CpqSettings {
    pub hidden_sizes: Vec<usize>,
    pub vae_hidden: usize,
    pub num_q: usize,
    pub gamma: f64,
    pub tau: f64,
    pub beta: f64,
    pub sample_action_num: usize,
    /// `qc_thres = qc_scalar · q_thres`: the level the OOD penalty's multiplier aims the cost of OOD actions at.
    pub qc_scalar: f64,
    pub actor_lr: f64,
    pub critic_lr: f64,
    pub vae_lr: f64,
    pub alpha_lr: f64,
    pub reward_scale: f64,
    pub cost_scale: f64,
    pub batch_size: usize,
    pub seed: u64,
}

impl Default for CpqSettings {
    fn default() -> Self {
        CpqSettings {
            hidden_sizes: vec![256, 256],
            vae_hidden: 400,
            num_q: 2,
            gamma: 0.99,
            tau: 0.005,
            beta: 0.5,
            sample_action_num: 10,
            qc_scalar: 1.5,
            actor_lr: 1e-4,
            critic_lr: 1e-3,
            vae_lr: 1e-3,
            alpha_lr: 1e-4,
            reward_scale: 0.1,
            cost_scale: 1.0,
            batch_size: 512,
            seed: 0,
        }
    }
}

pub struct CpqLearner {
    pub settings: CpqSettings,
    pub actor: SquashedGaussianActor,
    pub vae: Vae,
    critic: Ensemble,
    critic_target: Ensemble,
    cost_critic: Ensemble,
    cost_critic_target: Ensemble,
    actor_optim: Adam,
    critic_optim: Adam,
    cost_critic_optim: Adam,
    vae_optim: Adam,
    pub log_alpha: f64,
    q_thres: f64,
    qc_thres: f64,
    noise: Noise,
    data: Transitions,
    obs_dim: usize,
}

impl CpqLearner {
    /// A learner for the cost threshold `kappa` of a task whose episodes last `episode_len` steps.
    pub fn new(settings: CpqSettings, data: &Demonstrations, kappa: f64, episode_len: usize) -> anyhow::Result<Self> {
        Self::on_device(settings, data, kappa, episode_len, &dsrl_policy::Device::Cpu)
    }

    /// As [`CpqLearner::new`], training on `device` (networks initialised on the CPU from the seed, then moved).
    pub fn on_device(
        settings: CpqSettings,
        data: &Demonstrations,
        kappa: f64,
        episode_len: usize,
        device: &dsrl_policy::Device,
    ) -> anyhow::Result<Self> {
        let (o, a) = (data.obs_dim, data.act_dim);
        let mut noise = Noise::seeded(settings.seed);
        let actor = SquashedGaussianActor::new(o, a, &settings.hidden_sizes, &mut noise)?.to_device(device)?;
        let critic =
            Ensemble::new("critic", o + a, &settings.hidden_sizes, settings.num_q, &mut noise)?.to_device(device)?;
        let vae = Vae::new(o, a, settings.vae_hidden, 2 * a, MAX_ACTION, &mut noise)?.to_device(device)?;
        let cost_critic = Ensemble::new("cost_critic", o + a, &settings.hidden_sizes, settings.num_q, &mut noise)?
            .to_device(device)?;
        let q_thres = qc_threshold(kappa, settings.gamma, episode_len);
        Ok(CpqLearner {
            actor_optim: Adam::new(actor.named_vars(), settings.actor_lr, None)?,
            critic_optim: Adam::new(critic.named_vars(), settings.critic_lr, None)?,
            cost_critic_optim: Adam::new(cost_critic.named_vars(), settings.critic_lr, None)?,
            vae_optim: Adam::new(vae.named_vars(), settings.vae_lr, None)?,
            critic_target: critic.copy()?,
            cost_critic_target: cost_critic.copy()?,
            log_alpha: 0.0,
            q_thres,
            qc_thres: settings.qc_scalar * q_thres,
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

    /// `max_action · tanh(u)` for a fresh draw of the current actor at `obs` (OSRL's `_actor_forward`).
    fn act_sampled(&mut self, obs: &Tensor) -> anyhow::Result<Tensor> {
        let sample = self.actor.sample_with(obs, &mut self.noise)?;
        Ok(sample.action.affine(MAX_ACTION, 0.0)?)
    }

    /// 1 where `qc ≤ threshold`, else 0 (no gradient).
    fn within(qc: &Tensor, threshold: f64) -> anyhow::Result<Tensor> {
        Ok(qc.le(threshold)?.to_dtype(DType::F32)?)
    }
}

impl ThresholdLearner for CpqLearner {
    fn modules(&self) -> Vec<(&'static str, Vec<(String, Var)>)> {
        vec![
            ("actor", self.actor.named_vars()),
            ("critic", self.critic.named_vars()),
            ("cost_critic", self.cost_critic.named_vars()),
            ("vae", self.vae.named_vars()),
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

        // Reward critic: the constraint-penalized backup.
        let next_act = self.act_sampled(&batch.next_obs)?.detach();
        let next_input = concat(&batch.next_obs, &next_act)?;
        let q_next = Ensemble::min(&self.critic_target.values(&next_input)?)?;
        let qc_next = Ensemble::min(&self.cost_critic_target.values(&next_input)?)?;
        let continues = batch.done.affine(-s.gamma, s.gamma)?;
        let backup = batch
            .reward
            .add(&continues.mul(&Self::within(&qc_next, self.q_thres)?)?.mul(&q_next)?)?
            .detach();
        let critic_loss = Ensemble::loss(&self.critic.values(&input)?, &backup)?;
        self.critic_optim.step(&critic_loss.backward()?)?;

        // Cost critic, with OSRL's (gradient-free) penalty on the cost of out-of-distribution actions.
        let next_act = self.act_sampled(&batch.next_obs)?.detach();
        let qc_next = Ensemble::min(&self.cost_critic_target.values(&concat(&batch.next_obs, &next_act)?)?)?;
        let backup_c = batch.cost.add(&qc_next.affine(s.gamma, 0.0)?)?.detach();
        let n = s.sample_action_num;
        // Draws are sample-major (`pi_dist.sample([n])`): row k·b + i is draw k at state i, pre-tanh as OSRL.
        let (mean, log_std) = self.actor.distribution(&batch.obs)?;
        let (mean, std) = (mean.detach(), log_std.exp()?.detach());
        let stacked_obs = Tensor::cat(&vec![&batch.obs; n], 0)?;
        let eps = normals(&mut self.noise, n * b, self.actor.act_dim, self.data.device())?;
        let ood_actions = Tensor::cat(&vec![&mean; n], 0)?.add(&Tensor::cat(&vec![&std; n], 0)?.mul(&eps)?)?;
        let qc_sampled = Ensemble::min(&self.cost_critic_target.values(&concat(&stacked_obs, &ood_actions)?)?)?;
        let (z_mean, z_std) = self.vae.encode(&stacked_obs, &ood_actions)?;
        let kl = z_std
            .sqr()?
            .log()?
            .affine(1.0, 1.0)?
            .sub(&z_mean.sqr()?)?
            .sub(&z_std.sqr()?)?
            .mean(1)?
            .affine(-0.5, 0.0)?;
        let kl_values: Vec<f32> = kl.to_vec1()?;
        let cut = quantile(&kl_values, 0.75);
        let qc_sampled: Vec<f32> = qc_sampled.to_vec1()?;
        // mean over draws of 1[KL ≥ quantile]·Qc, then over states.
        let ood_mean = kl_values
            .iter()
            .zip(&qc_sampled)
            .map(|(&k, &q)| if k >= cut { f64::from(q) } else { 0.0 })
            .sum::<f64>()
            / (n * b) as f64;
        let alpha = self.log_alpha.exp();
        let cost_critic_loss = Ensemble::loss(&self.cost_critic.values(&input)?, &backup_c)?;
        self.cost_critic_optim.step(&cost_critic_loss.backward()?)?;
        let cost_critic_loss = f64::from(cost_critic_loss.to_scalar::<f32>()?) - alpha * (ood_mean - self.qc_thres);
        self.log_alpha = (self.log_alpha + s.alpha_lr * alpha * (self.qc_thres - ood_mean)).clamp(-5.0, 5.0);

        // Actor: reward value only where the cost value keeps within the threshold.
        let action = self.act_sampled(&batch.obs)?;
        let policy_input = concat(&batch.obs, &action)?;
        let q = Ensemble::min(&self.critic.values(&policy_input)?)?;
        let qc = Ensemble::min(&self.cost_critic.values(&policy_input)?)?;
        let safe = Self::within(&qc, self.q_thres)?;
        let actor_loss = safe.mul(&q)?.mean_all()?.neg()?;
        self.actor_optim.step(&actor_loss.backward()?)?;

        soft_update(&self.critic_target.named_vars(), &self.critic.named_vars(), s.tau)?;
        soft_update(
            &self.cost_critic_target.named_vars(),
            &self.cost_critic.named_vars(),
            s.tau,
        )?;
        let safe_fraction = f64::from(safe.mean_all()?.to_scalar::<f32>()?);
        Ok(vec![
            ("vae", f64::from(vae_loss.to_scalar::<f32>()?)),
            ("critic", f64::from(critic_loss.to_scalar::<f32>()?)),
            ("cost_critic", cost_critic_loss),
            ("actor", f64::from(actor_loss.to_scalar::<f32>()?)),
            ("alpha", self.log_alpha.exp()),
            ("qc_ood", ood_mean),
            ("safe_fraction", safe_fraction),
        ])
    }

    fn batch_size(&self) -> usize {
        self.settings.batch_size
    }

    fn qc_threshold(&self) -> f64 {
        self.q_thres
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

    fn small(seed: u64) -> CpqSettings {
        CpqSettings {
            hidden_sizes: vec![16, 16],
            vae_hidden: 16,
            batch_size: 32,
            seed,
            ..CpqSettings::default()
        }
    }

    #[test]
    fn a_few_steps_train_every_part_deterministically_and_write_what_the_evaluator_plays() {
        let data = toy();
        let mut learner = CpqLearner::new(small(3), &data, 2.0, 10).unwrap();
        let (first, last) = run(&mut learner, 60);
        assert!(figure(&last, "vae") < figure(&first, "vae"), "{first:?} -> {last:?}");
        assert!((0.0..=1.0).contains(&figure(&last, "safe_fraction")));
        // α moved from 1 and stays within e^±5.
        let alpha = figure(&last, "alpha");
        assert!(alpha != 1.0 && ((-5f64).exp()..=5f64.exp()).contains(&alpha), "{alpha}");
        // qc_thres is 1.5 × the per-step threshold.
        assert!((learner.qc_thres - 1.5 * learner.qc_threshold()).abs() < 1e-12);

        let mut again = CpqLearner::new(small(3), &data, 2.0, 10).unwrap();
        run(&mut again, 60);
        assert_eq!(
            first_weights(learner.actor.named_vars()),
            first_weights(again.actor.named_vars())
        );

        let obs = [0.3f32, 0.7];
        let o = Tensor::from_vec(obs.to_vec(), (1, 2), &dsrl_policy::Device::Cpu).unwrap();
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

    #[test]
    fn the_reward_backup_drops_the_value_of_next_states_over_the_cost_threshold() {
        let qc = Tensor::new(&[0.5f32, 3.0, 1.0], &dsrl_policy::Device::Cpu).unwrap();
        let mask: Vec<f32> = CpqLearner::within(&qc, 1.0).unwrap().to_vec1().unwrap();
        assert_eq!(mask, vec![1.0, 0.0, 1.0]);
    }
}
