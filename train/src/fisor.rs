//! FISOR (Zheng et al., ICLR 2024, "Safe Offline Reinforcement Learning with Feasibility-Guided Diffusion Model";
//! its JAX code's `jaxrl5/agents/fisor/fisor.py` and `configs/train_config.py`). Beyond the paper's baselines: a hard
//! constraint learned as a feasibility value, and a diffusion actor trained by weighted noise regression. One model
//! for every threshold (FISOR has no threshold input; the evaluator side is `dsrl_policy::diffusion`).
//!
//! Costs are recoded `c = 25` where the step costs anything and `−1` where it is free; rewards are scaled by
//! `horizon / (max − min reward return)` of the task's normalization constants (`normalize_returns`). One step, on
//! one batch of 2048 drawn uniformly:
//! 1. the actor twice, on each half (1024 rows): `t ~ U{0..T−1}`, `ε ~ N(0, I)`,
//!    `x_t = √ᾱ_t·a + √(1 − ᾱ_t)·ε`, loss `mean(w · Σ_d (ε̂(s, x_t, t) − ε)²)` with dropout, where
//!    `w = [V_h(s) > 0]·clip(e^{5(V_h − Q_h)}, 0, 150) + [V_h ≤ 0][Q_h ≤ 0]·clip(e^{3(Q_r − V_r)}, 0, 100)`
//!    (`Q_r` the minimum and `Q_h` the maximum over the target pairs): in the infeasible region, actions that
//!    lower the feasibility value; in the feasible one, actions with high reward advantage; nothing elsewhere.
//!    AdamW (decay 0) with the rate on a cosine to zero over 3·10⁶ actor updates; the EMA actor follows at τ 0.001;
//! 2. on the first 256 rows: `V_r` by expectile 0.9 on `min Q_r' − V_r`; `Q_r` on `r + γ·mask·V_r(s′)`; `V_h` by
//!    the reversed expectile (0.1) on `max Q_h' − V_h`; `Q_h` on the reachability target
//!    `mask·((1 − γ)·c + γ·max(c, V_h(s′))) + (1 − mask)·c`; each pair's target copy follows at τ 0.005.
//!
//! `mask` is 0 at an episode's end, a time limit included (as FISOR's `masks`). The checkpoint holds the EMA actor
//! and the target feasibility pair, which picks the candidate with the lowest `max Q_h` (FISOR's `minqc`).
//!
//! Departures: the critics start from PyTorch's default initialisation (FISOR: xavier-uniform); batches come from
//! the seeded generator, and JAX's random numbers cannot be matched.

use std::path::Path;

use dsrl_policy::adam::Adam;
use dsrl_policy::checkpoint::{self, Architecture, Conditioning, DiffusionSampler, PolicyConfig};
use dsrl_policy::diffusion::{CandidateChoice, DiffusionShape, NoiseNet, Schedule};
use dsrl_policy::mlp::{Activation, Mlp};
use dsrl_policy::noise::Noise;
use dsrl_policy::offline::{Ensemble, concat, soft_update};
use dsrl_policy::{DType, Tensor};

use crate::offline::{Batch, EveryThresholdLearner, Figures, Transitions, expectile_loss};
use crate::{Demonstrations, MAX_ACTION};

/// FISOR's configuration (`configs/train_config.py`, `FISOR.create`'s defaults).
#[derive(Debug, Clone, PartialEq)]
pub struct FisorSettings {
    pub time_dim: usize,
    pub cond_sizes: Vec<usize>,
    pub hidden_dim: usize,
    pub num_blocks: usize,
    pub dropout: f64,
    pub diffusion_steps: usize,
    pub beta_min: f64,
    pub beta_max: f64,
    pub candidates: usize,
    pub critic_hidden_sizes: Vec<usize>,
    pub critic_members: usize,
    pub actor_lr: f64,
    pub critic_lr: f64,
    pub value_lr: f64,
    /// Actor updates over which the actor's rate decays to zero.
    pub decay_steps: u64,
    /// Rows per actor update (two per step) and per critic update.
    pub actor_batch: usize,
    pub critic_batch: usize,
    pub gamma: f64,
    pub tau: f64,
    pub actor_tau: f64,
    /// Expectile of `V_r` (upper) and of `V_h` (reversed: `1 −` this).
    pub reward_expectile: f64,
    pub cost_expectile: f64,
    pub reward_temperature: f64,
    pub cost_temperature: f64,
    pub reward_weight_max: f64,
    pub cost_weight_max: f64,
    /// The recoded cost of a step that costs anything (`cost_scale`); a free step is −1.
    pub cost_scale: f64,
    /// What rewards are multiplied by (FISOR: horizon over the task's reward-return range).
    pub reward_scale: f64,
    pub seed: u64,
}

impl Default for FisorSettings {
    fn default() -> Self {
        FisorSettings {
            time_dim: 64,
            cond_sizes: vec![128, 128],
            hidden_dim: 256,
            num_blocks: 3,
            dropout: 0.1,
            diffusion_steps: 5,
            beta_min: 0.1,
            beta_max: 10.0,
            candidates: 16,
            critic_hidden_sizes: vec![256, 256],
            critic_members: 2,
            actor_lr: 3e-4,
            critic_lr: 3e-4,
            value_lr: 3e-4,
            decay_steps: 3_000_000,
            actor_batch: 1024,
            critic_batch: 256,
            gamma: 0.99,
            tau: 0.005,
            actor_tau: 0.001,
            reward_expectile: 0.9,
            cost_expectile: 0.9,
            reward_temperature: 3.0,
            cost_temperature: 5.0,
            reward_weight_max: 100.0,
            cost_weight_max: 150.0,
            cost_scale: 25.0,
            reward_scale: 1.0,
            seed: 0,
        }
    }
}

impl FisorSettings {
    /// `horizon / (max − min)` of the task's reward-return normalization constants (FISOR's `normalize_returns`).
    pub fn reward_scale_for(task: &dsrl_suite::Task) -> f64 {
        let range = task.max_episode_reward - task.min_episode_reward;
        if range > 0.0 {
            f64::from(task.max_episode_steps) / range
        } else {
            1.0
        }
    }
}

pub struct FisorLearner {
    pub settings: FisorSettings,
    pub actor: NoiseNet,
    pub ema_actor: NoiseNet,
    pub reward_q: Ensemble,
    pub cost_q: Ensemble,
    reward_q_target: Ensemble,
    cost_q_target: Ensemble,
    pub reward_v: Mlp,
    pub cost_v: Mlp,
    schedule: Schedule,
    actor_optim: Adam,
    reward_q_optim: Adam,
    cost_q_optim: Adam,
    reward_v_optim: Adam,
    cost_v_optim: Adam,
    noise: Noise,
    data: Transitions,
    actor_updates: u64,
}

impl FisorLearner {
    pub fn new(settings: FisorSettings, data: &Demonstrations) -> anyhow::Result<Self> {
        Self::on_device(settings, data, &dsrl_policy::Device::Cpu)
    }

    /// As [`FisorLearner::new`], training on `device` (networks initialised on the CPU from the seed, then moved).
    pub fn on_device(
        settings: FisorSettings,
        data: &Demonstrations,
        device: &dsrl_policy::Device,
    ) -> anyhow::Result<Self> {
        let (o, a) = (data.obs_dim, data.act_dim);
        anyhow::ensure!(
            settings.actor_batch > 0 && settings.critic_batch > 0 && settings.critic_batch <= 2 * settings.actor_batch,
            "fisor: batches must be positive and the critic batch within the two actor halves"
        );
        anyhow::ensure!(
            (1..=1000).contains(&settings.diffusion_steps),
            "fisor: 1 to 1000 diffusion steps"
        );
        let mut noise = Noise::seeded(settings.seed);
        let shape = DiffusionShape {
            obs_dim: o,
            act_dim: a,
            time_dim: settings.time_dim,
            cond_sizes: settings.cond_sizes.clone(),
            hidden_dim: settings.hidden_dim,
            num_blocks: settings.num_blocks,
            layer_norm: true,
        };
        let actor = NoiseNet::new(shape, &mut noise)?.to_device(device)?;
        let ema_actor = actor.copy()?;
        let members = settings.critic_members;
        let hidden = &settings.critic_hidden_sizes;
        let reward_q = Ensemble::new("reward_q", o + a, hidden, members, &mut noise)?.to_device(device)?;
        let cost_q = Ensemble::new("cost_q", o + a, hidden, members, &mut noise)?.to_device(device)?;
        let mut v_sizes = vec![o];
        v_sizes.extend(hidden);
        v_sizes.push(1);
        let reward_v = Mlp::pytorch_default("reward_v", &v_sizes, Activation::Relu, &mut noise)?.to_device(device)?;
        let cost_v = Mlp::pytorch_default("cost_v", &v_sizes, Activation::Relu, &mut noise)?.to_device(device)?;
        Ok(FisorLearner {
            actor_optim: Adam::adamw(actor.named_vars("actor"), settings.actor_lr, 0.0, None)?,
            reward_q_optim: Adam::new(reward_q.named_vars(), settings.critic_lr, None)?,
            cost_q_optim: Adam::new(cost_q.named_vars(), settings.critic_lr, None)?,
            reward_v_optim: Adam::new(reward_v.named_vars(), settings.value_lr, None)?,
            cost_v_optim: Adam::new(cost_v.named_vars(), settings.value_lr, None)?,
            reward_q_target: reward_q.copy()?,
            cost_q_target: cost_q.copy()?,
            schedule: Schedule::vp(settings.diffusion_steps, settings.beta_min, settings.beta_max),
            data: Transitions::new(data, device)?,
            actor,
            ema_actor,
            reward_q,
            cost_q,
            reward_v,
            cost_v,
            noise,
            actor_updates: 0,
            settings,
        })
    }

    /// The actor's learning rate at actor update `k` (optax's `cosine_decay_schedule` to zero).
    pub fn actor_lr(&self, k: u64) -> f64 {
        let s = &self.settings;
        let t = k.min(s.decay_steps) as f64 / s.decay_steps.max(1) as f64;
        s.actor_lr * 0.5 * (1.0 + (std::f64::consts::PI * t).cos())
    }

    /// The recoded cost: `cost_scale` where the step costs anything, −1 where it is free.
    pub fn recode_cost(cost: &Tensor, cost_scale: f64) -> anyhow::Result<Tensor> {
        Ok(cost.gt(0.0)?.to_dtype(DType::F32)?.affine(cost_scale + 1.0, -1.0)?)
    }

    /// The actor's per-row weights from the target pairs and the value networks (no gradient).
    pub fn actor_weights(&self, obs: &Tensor, act: &Tensor) -> anyhow::Result<Tensor> {
        let s = &self.settings;
        let input = concat(obs, act)?;
        let q = Ensemble::min(&self.reward_q_target.values(&input)?)?;
        let v = self.reward_v.forward(obs)?.squeeze(1)?;
        let qc = Ensemble::max(&self.cost_q_target.values(&input)?)?;
        let vc = self.cost_v.forward(obs)?.squeeze(1)?;
        Self::weights(s, &q, &v, &qc, &vc)
    }

    /// `[vc > 0]·clip(e^{κ_c(vc − qc)}, 0, W_c) + [vc ≤ 0][qc ≤ 0]·clip(e^{κ_r(q − v)}, 0, W_r)`.
    pub fn weights(s: &FisorSettings, q: &Tensor, v: &Tensor, qc: &Tensor, vc: &Tensor) -> anyhow::Result<Tensor> {
        let infeasible = vc.gt(0.0)?.to_dtype(DType::F32)?;
        let feasible = vc
            .le(0.0)?
            .to_dtype(DType::F32)?
            .mul(&qc.le(0.0)?.to_dtype(DType::F32)?)?;
        // Clipped before the indicator multiplies it: an overflow to infinity becomes the clip, never 0·∞.
        let cost_w = vc
            .sub(qc)?
            .affine(s.cost_temperature, 0.0)?
            .exp()?
            .minimum(s.cost_weight_max)?;
        let reward_w = q
            .sub(v)?
            .affine(s.reward_temperature, 0.0)?
            .exp()?
            .minimum(s.reward_weight_max)?;
        Ok(infeasible.mul(&cost_w)?.add(&feasible.mul(&reward_w)?)?.detach())
    }

    /// The weighted noise-regression loss on `(obs, act)` with the given step indices and noise.
    pub fn actor_loss(
        &mut self,
        obs: &Tensor,
        act: &Tensor,
        weights: &Tensor,
        steps: &[usize],
        eps: &Tensor,
    ) -> anyhow::Result<Tensor> {
        let device = obs.device().clone();
        let rows = steps.len();
        let column = |f: &dyn Fn(usize) -> f64| {
            let v: Vec<f32> = steps.iter().map(|&t| f(t) as f32).collect();
            Tensor::from_vec(v, (rows, 1), &device)
        };
        let signal = column(&|t| self.schedule.alpha_hats[t].sqrt())?;
        let noise_level = column(&|t| (1.0 - self.schedule.alpha_hats[t]).sqrt())?;
        let times = column(&|t| t as f64)?;
        let noised = act.broadcast_mul(&signal)?.add(&eps.broadcast_mul(&noise_level)?)?;
        let rate = self.settings.dropout;
        let predicted = self
            .actor
            .forward(obs, &noised, &times, Some((rate, &mut self.noise)))?;
        let per_row = predicted.sub(eps)?.sqr()?.sum(1)?;
        Ok(weights.mul(&per_row)?.mean_all()?)
    }

    fn update_actor(&mut self, obs: &Tensor, act: &Tensor) -> anyhow::Result<f64> {
        let rows = obs.dim(0)?;
        let weights = self.actor_weights(obs, act)?;
        let t_max = self.schedule.steps() as u64;
        let steps: Vec<usize> = (0..rows).map(|_| (self.noise.next_u64() % t_max) as usize).collect();
        let eps = Tensor::from_vec(self.noise.normals_f32(rows * act.dim(1)?), act.shape(), obs.device())?;
        let loss = self.actor_loss(obs, act, &weights, &steps, &eps)?;
        self.actor_optim.lr = self.actor_lr(self.actor_updates);
        self.actor_optim.step(&loss.backward()?)?;
        self.actor_updates += 1;
        soft_update(
            &self.ema_actor.named_vars("actor"),
            &self.actor.named_vars("actor"),
            self.settings.actor_tau,
        )?;
        Ok(f64::from(loss.to_scalar::<f32>()?))
    }

    /// One training step on `batch` (2 × the actor batch rows; rewards scaled, costs raw).
    pub fn update(&mut self, batch: &Batch) -> anyhow::Result<Figures> {
        let s = self.settings.clone();
        let half = s.actor_batch;
        let mut actor_loss = 0.0;
        for k in 0..2 {
            let obs = batch.obs.narrow(0, k * half, half)?;
            let act = batch.act.narrow(0, k * half, half)?;
            actor_loss += self.update_actor(&obs, &act)? / 2.0;
        }

        let rows = |t: &Tensor| t.narrow(0, 0, s.critic_batch);
        let (obs, act, next_obs) = (rows(&batch.obs)?, rows(&batch.act)?, rows(&batch.next_obs)?);
        let (reward, cost, done) = (rows(&batch.reward)?, rows(&batch.cost)?, rows(&batch.done)?);
        let input = concat(&obs, &act)?;
        let mask = done.affine(-1.0, 1.0)?;

        // Reward value (upper expectile), then the reward pair on the updated value.
        let q = Ensemble::min(&self.reward_q_target.values(&input)?)?.detach();
        let reward_v_loss = expectile_loss(&q.sub(&self.reward_v.forward(&obs)?.squeeze(1)?)?, s.reward_expectile)?;
        self.reward_v_optim.step(&reward_v_loss.backward()?)?;
        let next_v = self.reward_v.forward(&next_obs)?.squeeze(1)?.detach();
        let target = reward.add(&mask.affine(s.gamma, 0.0)?.mul(&next_v)?)?.detach();
        let reward_q_loss = Ensemble::mean_loss(&self.reward_q.values(&input)?, &target)?;
        self.reward_q_optim.step(&reward_q_loss.backward()?)?;
        soft_update(&self.reward_q_target.named_vars(), &self.reward_q.named_vars(), s.tau)?;

        // Feasibility value (reversed expectile: a soft minimum over actions), then the pair on the reachability
        // target.
        let qc = Ensemble::max(&self.cost_q_target.values(&input)?)?.detach();
        let cost_v_loss = expectile_loss(
            &qc.sub(&self.cost_v.forward(&obs)?.squeeze(1)?)?,
            1.0 - s.cost_expectile,
        )?;
        self.cost_v_optim.step(&cost_v_loss.backward()?)?;
        let next_vc = self.cost_v.forward(&next_obs)?.squeeze(1)?.detach();
        let c = Self::recode_cost(&cost, s.cost_scale)?;
        let target = Self::reachability_target(&c, &next_vc, &mask, s.gamma)?;
        let cost_q_loss = Ensemble::mean_loss(&self.cost_q.values(&input)?, &target)?;
        self.cost_q_optim.step(&cost_q_loss.backward()?)?;
        soft_update(&self.cost_q_target.named_vars(), &self.cost_q.named_vars(), s.tau)?;

        let scalar = |t: &Tensor| -> anyhow::Result<f64> { Ok(f64::from(t.to_scalar::<f32>()?)) };
        Ok(vec![
            ("actor", actor_loss),
            ("reward_v", scalar(&reward_v_loss)?),
            ("reward_q", scalar(&reward_q_loss)?),
            ("cost_v", scalar(&cost_v_loss)?),
            ("cost_q", scalar(&cost_q_loss)?),
            ("actor_lr", self.actor_optim.lr),
        ])
    }

    /// `mask·((1 − γ)·c + γ·max(c, V_h(s′))) + (1 − mask)·c`.
    pub fn reachability_target(c: &Tensor, next_vc: &Tensor, mask: &Tensor, gamma: f64) -> anyhow::Result<Tensor> {
        let running = c
            .affine(1.0 - gamma, 0.0)?
            .add(&c.maximum(next_vc)?.affine(gamma, 0.0)?)?;
        let ended = mask.affine(-1.0, 1.0)?;
        Ok(mask.mul(&running)?.add(&ended.mul(c)?)?.detach())
    }
}

impl EveryThresholdLearner for FisorLearner {
    fn step(&mut self) -> anyhow::Result<Figures> {
        let s = &self.settings;
        let batch = self
            .data
            .sample(2 * s.actor_batch, s.reward_scale, 1.0, &mut self.noise)?;
        self.update(&batch)
    }

    /// Writes the evaluator's `diffusion` checkpoint (the EMA actor, the target feasibility pair; one model for
    /// every threshold) with `training` recorded.
    fn write(&self, dir: &Path, task: &str, training: serde_json::Value) -> anyhow::Result<()> {
        let s = &self.settings;
        let config = PolicyConfig {
            format: checkpoint::FORMAT.into(),
            task: task.to_owned(),
            obs_dim: self.actor.shape.obs_dim,
            act_dim: self.actor.shape.act_dim,
            architecture: Architecture::Diffusion {
                time_dim: s.time_dim,
                cond_sizes: s.cond_sizes.clone(),
                hidden_dim: s.hidden_dim,
                num_blocks: s.num_blocks,
                layer_norm: true,
                critic_hidden_sizes: s.critic_hidden_sizes.clone(),
                critic_members: s.critic_members,
                max_action: MAX_ACTION,
                sampler: DiffusionSampler::Ddpm {
                    steps: s.diffusion_steps,
                    beta_min: s.beta_min,
                    beta_max: s.beta_max,
                    clip: true,
                    temperature: 1.0,
                    candidates: s.candidates,
                    choice: CandidateChoice::MinCostQ,
                },
            },
            observation_normalization: None,
            conditioning: Conditioning::Unconditioned,
            training: Some(training),
        };
        let mut tensors = dsrl_policy::tensors_of(self.ema_actor.named_vars("actor"));
        tensors.extend(dsrl_policy::tensors_of(self.cost_q_target.named_vars()));
        checkpoint::write(dir, &config, &tensors)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::offline::tests::{assert_falls, first_weights, read_back, run_steps, toy};

    fn small(seed: u64) -> FisorSettings {
        FisorSettings {
            time_dim: 8,
            cond_sizes: vec![16, 16],
            hidden_dim: 16,
            num_blocks: 2,
            candidates: 4,
            critic_hidden_sizes: vec![16, 16],
            actor_batch: 32,
            critic_batch: 16,
            actor_lr: 3e-3,
            critic_lr: 3e-3,
            value_lr: 3e-3,
            seed,
            ..FisorSettings::default()
        }
    }

    fn t(values: &[f32]) -> Tensor {
        Tensor::new(values, &dsrl_policy::Device::Cpu).unwrap()
    }

    #[test]
    fn the_weights_gate_by_feasibility_as_worked_by_hand() {
        let s = FisorSettings::default();
        // Rows: infeasible (vc 0.2 > 0); feasible and safe (vc, qc ≤ 0); vc ≤ 0 but qc > 0 (weight 0); infeasible
        // with a huge gap (clipped at 150); feasible with a huge advantage (clipped at 100).
        let q = t(&[1.0, 2.0, 2.0, 0.0, 50.0]);
        let v = t(&[0.0, 1.9, 0.0, 0.0, 0.0]);
        let qc = t(&[0.1, -0.5, 0.3, -100.0, -1.0]);
        let vc = t(&[0.2, -0.4, -0.1, 1.0, -2.0]);
        let w = FisorLearner::weights(&s, &q, &v, &qc, &vc)
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let want = [(5.0f64 * 0.1).exp(), (3.0f64 * 0.1).exp(), 0.0, 150.0, 100.0];
        for (g, e) in w.iter().zip(want) {
            assert!((f64::from(*g) - e).abs() < 1e-4 * e.max(1.0), "{w:?} vs {want:?}");
        }
    }

    #[test]
    fn the_reachability_target_and_the_recoded_cost_are_fisors() {
        let c = FisorLearner::recode_cost(&t(&[0.0, 1.0, 0.5, 0.0]), 25.0).unwrap();
        assert_eq!(c.to_vec1::<f32>().unwrap(), vec![-1.0, 25.0, 25.0, -1.0]);
        let next_vc = t(&[3.0, -2.0, 30.0, 3.0]);
        let mask = t(&[1.0, 1.0, 1.0, 0.0]);
        let target = FisorLearner::reachability_target(&c, &next_vc, &mask, 0.99).unwrap();
        // (1−γ)c + γ·max(c, V'): −0.01 + 2.97; 0.25 + 24.75; 0.25 + 29.7; ended: c.
        let want = [-0.01 + 0.99 * 3.0, 0.25 + 0.99 * 25.0, 0.25 + 0.99 * 30.0, -1.0];
        for (g, e) in target.to_vec1::<f32>().unwrap().iter().zip(want) {
            assert!((f64::from(*g) - e).abs() < 1e-5, "{g} vs {e}");
        }
        let learner = FisorLearner::new(small(1), &toy()).unwrap();
        assert!((learner.actor_lr(0) - 3e-3).abs() < 1e-15);
        assert!((learner.actor_lr(1_500_000) - 1.5e-3).abs() < 1e-12);
    }

    #[test]
    fn the_actor_loss_is_the_weighted_noise_error_worked_by_hand() {
        let mut learner = FisorLearner::new(
            FisorSettings {
                dropout: 0.0,
                ..small(2)
            },
            &toy(),
        )
        .unwrap();
        let cpu = &dsrl_policy::Device::Cpu;
        let obs = Tensor::new(&[[0.2f32, 0.4], [0.6, 0.1]], cpu).unwrap();
        let act = Tensor::new(&[[0.1f32], [-0.3]], cpu).unwrap();
        let eps = Tensor::new(&[[0.5f32], [-1.0]], cpu).unwrap();
        let weights = t(&[2.0, 0.5]);
        let steps = [0usize, 4];
        let loss = learner
            .actor_loss(&obs, &act, &weights, &steps, &eps)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        let s = Schedule::vp(5, 0.1, 10.0);
        let mut want = 0.0;
        for (i, (&step, (a, e))) in steps.iter().zip([(0.1f64, 0.5f64), (-0.3, -1.0)]).enumerate() {
            let x = s.alpha_hats[step].sqrt() * a + (1.0 - s.alpha_hats[step]).sqrt() * e;
            let row = obs.narrow(0, i, 1).unwrap();
            let predicted = learner
                .actor
                .forward(
                    &row,
                    &Tensor::new(&[[x as f32]], cpu).unwrap(),
                    &Tensor::new(&[[step as f32]], cpu).unwrap(),
                    None,
                )
                .unwrap()
                .to_vec2::<f32>()
                .unwrap()[0][0];
            want += [2.0, 0.5][i] * (f64::from(predicted) - e).powi(2) / 2.0;
        }
        assert!((f64::from(loss) - want).abs() < 1e-5, "{loss} vs {want}");
    }

    #[test]
    fn a_few_steps_train_deterministically_and_the_checkpoint_plays_the_most_feasible_candidate() {
        let data = toy();
        let mut learner = FisorLearner::new(small(3), &data).unwrap();
        let (first, last) = run_steps(|| learner.step(), 60);
        assert_falls(&first, &last, &["reward_q", "actor"]);
        let mut again = FisorLearner::new(small(3), &data).unwrap();
        for _ in 0..60 {
            again.step().unwrap();
        }
        assert_eq!(
            first_weights(learner.ema_actor.named_vars("actor")),
            first_weights(again.ema_actor.named_vars("actor"))
        );

        // Written, read back as the evaluator reads it, and played: the same action for the same episode seed,
        // within [−1, 1], and the candidate of lowest max Q_h among those the sampler drew.
        let (_, _, policy) = read_back(&learner, 60);
        let play = |seed: u64| {
            let mut rollout = policy.rollout(10.0, 1).unwrap();
            rollout.start_episode(0, seed).unwrap();
            rollout.act(&[0], &[0.3, 0.7]).unwrap()
        };
        let action = play(11);
        assert_eq!(action, play(11));
        assert!(action[0].abs() <= 1.0);
        let cpu = &dsrl_policy::Device::Cpu;
        let obs = dsrl_policy::offline::repeat_rows(&Tensor::new(&[[0.3f32, 0.7]], cpu).unwrap(), 4).unwrap();
        let sampler = dsrl_policy::diffusion::Sampler {
            schedule: Schedule::vp(5, 0.1, 10.0),
            candidates: 4,
            clip: true,
            temperature: 1.0,
        };
        let mut g = Noise::seeded(11);
        let candidates = sampler.sample(&learner.ema_actor, &obs, &mut [&mut g]).unwrap();
        let qc = Ensemble::max(
            &learner
                .cost_q_target
                .values(&concat(&obs, &candidates).unwrap())
                .unwrap(),
        )
        .unwrap();
        let qc = qc.to_vec1::<f32>().unwrap();
        let best = (0..4).min_by(|&i, &j| qc[i].total_cmp(&qc[j])).unwrap();
        let want = candidates.to_vec2::<f32>().unwrap()[best][0];
        assert!((action[0] - want).abs() < 1e-5, "{action:?} vs {want}");
    }
}
