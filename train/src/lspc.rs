//! LSPC (Koirala & Fleming, ICLR 2025, "Latent Safety-Constrained Policy Approach for Safe Offline Reinforcement
//! Learning"; its code's `lspc_iql.py` and `lspc_iql_configs.py`). Beyond the paper's baselines: a conditional VAE
//! learns the behaviour policy weighted towards safe actions, so its latent space holds safe behaviour, and a safety
//! encoder learns, by advantage-weighted regression, where in that space the reward is. One model for every
//! threshold (LSPC has no threshold input; the evaluator side is `dsrl_policy::latent`).
//!
//! Networks (hidden [256, 256], ReLU, PyTorch's default initialisation): the VAE (latent 32; encoder log σ in
//! [−4, 15]), the safety encoder (log σ in [−10, 2]), reward and cost critic pairs with target copies, value
//! networks `V_r`, `V_c`. One step on one batch of 1024, in LSPC's order:
//! 1. `V_r(s′)` and `max(V_c(s′), 0)` for the backups, before any update;
//! 2. `V_r` by expectile 0.7 on `min Q_r'(s, a) − V_r(s)` (the reward advantage, taken before the update);
//! 3. `Q_r` on `r + γ(1 − d)·V_r(s′)` (the mean of the pair's errors), then its target copy (τ 0.005);
//! 4. `V_c` by expectile 0.7 on `max(V_c(s), 0) − max(max Q_c'(s, a), 0)` (a lower expectile of the cost; that
//!    difference is the cost advantage); the safe mask is `[V_c < θ][Q_c' < θ]`;
//! 5. `Q_c` on `c + γ(1 − d)·max(V_c(s′), 0)`, then its target copy;
//! 6. the VAE on `w_c·(Σ_d (decode(s, z) − a)² + β·KL)`, `w_c = min(e^{2·cost advantage}, 200)·mask`,
//!    `KL = −½·mean_j(1 + log σ² − μ² − σ²)`, β 0.5;
//! 7. the safety encoder on `w_r·Σ_d (decode(s, max_latent·tanh(μ + σε)) − a)²`, `w_r = min(e^{2·reward
//!    advantage}, 200)`; the gradient reaches the decoder but only the encoder steps.
//!
//! `d` marks an episode's end, a time limit included (LSPC's `done = terminals + timeouts`). The checkpoint holds the
//! decoder and the safety encoder (LSPC-O: the encoder's latent, drawn per step from the episode's generator).
//! Departures: batches come from the seeded generator.

use std::path::Path;

use dsrl_policy::adam::Adam;
use dsrl_policy::checkpoint::{self, Architecture, Conditioning, PolicyConfig};
use dsrl_policy::latent::{LatentPolicy, LatentSource, SafetyEncoder};
use dsrl_policy::mlp::{Activation, Mlp};
use dsrl_policy::noise::Noise;
use dsrl_policy::offline::{Ensemble, concat, soft_update};
use dsrl_policy::vae::Vae;
use dsrl_policy::{DType, Tensor};

use crate::offline::{Batch, EveryThresholdLearner, Figures, Transitions, expectile_loss};
use crate::{Demonstrations, MAX_ACTION};

/// LSPC's configuration (`BCTrainConfig` and the task classes of `lspc_iql_configs.py`).
#[derive(Debug, Clone, PartialEq)]
pub struct LspcSettings {
    pub hidden: usize,
    pub latent_dim: usize,
    /// The safety encoder's latent bound (`max_latent_action`, equal to `vae_clamper` in every task's config).
    pub max_latent: f64,
    pub vae_beta: f64,
    pub iql_tau: f64,
    pub beta_reward: f64,
    pub beta_cost: f64,
    pub exp_adv_max_reward: f64,
    pub exp_adv_max_cost: f64,
    /// `safe_qc_vc_threshold` (999 outside MetaDrive, where the mask is then always 1).
    pub safe_threshold: f64,
    pub gamma: f64,
    pub tau: f64,
    pub lr: f64,
    pub batch_size: usize,
    pub seed: u64,
}

impl Default for LspcSettings {
    fn default() -> Self {
        LspcSettings {
            hidden: 256,
            latent_dim: 32,
            max_latent: 0.25,
            vae_beta: 0.5,
            iql_tau: 0.7,
            beta_reward: 2.0,
            beta_cost: 2.0,
            exp_adv_max_reward: 200.0,
            exp_adv_max_cost: 200.0,
            safe_threshold: 999.0,
            gamma: 0.99,
            tau: 0.005,
            lr: 3e-4,
            batch_size: 1024,
            seed: 0,
        }
    }
}

impl LspcSettings {
    /// The task's configuration: LSPC bounds the latent at 0.6 on the Bullet tasks but AntRun, at 0.25 elsewhere, and
    /// masks with threshold 0.02 on MetaDrive.
    pub fn for_task(task: &dsrl_suite::Task) -> LspcSettings {
        use dsrl_suite::Family;
        let id = task.id.as_str();
        let defaults = LspcSettings::default();
        LspcSettings {
            max_latent: if task.family == Family::Bullet && id != "OfflineAntRun-v0" {
                0.6
            } else {
                defaults.max_latent
            },
            safe_threshold: if task.family == Family::MetaDrive {
                0.02
            } else {
                defaults.safe_threshold
            },
            ..defaults
        }
    }
}

pub struct LspcLearner {
    pub settings: LspcSettings,
    pub vae: Vae,
    pub safety: SafetyEncoder,
    pub reward_q: Ensemble,
    pub cost_q: Ensemble,
    reward_q_target: Ensemble,
    cost_q_target: Ensemble,
    pub reward_v: Mlp,
    pub cost_v: Mlp,
    vae_optim: Adam,
    safety_optim: Adam,
    reward_q_optim: Adam,
    cost_q_optim: Adam,
    reward_v_optim: Adam,
    cost_v_optim: Adam,
    noise: Noise,
    data: Transitions,
}

impl LspcLearner {
    pub fn new(settings: LspcSettings, data: &Demonstrations) -> anyhow::Result<Self> {
        Self::on_device(settings, data, &dsrl_policy::Device::Cpu)
    }

    pub fn on_device(
        settings: LspcSettings,
        data: &Demonstrations,
        device: &dsrl_policy::Device,
    ) -> anyhow::Result<Self> {
        let (o, a) = (data.obs_dim, data.act_dim);
        anyhow::ensure!(
            settings.hidden > 0 && settings.latent_dim > 0 && settings.max_latent > 0.0,
            "lspc: hidden, latent_dim and max_latent must be positive"
        );
        let mut noise = Noise::seeded(settings.seed);
        let h = settings.hidden;
        let vae = Vae::new(o, a, h, settings.latent_dim, MAX_ACTION, &mut noise)?.to_device(device)?;
        let safety = SafetyEncoder {
            trunk: Mlp::pytorch_default("safety.trunk", &[o, h, h], Activation::Relu, &mut noise)?.to_device(device)?,
            mu: Mlp::pytorch_default("safety.mu", &[h, settings.latent_dim], Activation::Relu, &mut noise)?
                .to_device(device)?,
            log_std: Mlp::pytorch_default(
                "safety.log_std",
                &[h, settings.latent_dim],
                Activation::Relu,
                &mut noise,
            )?
            .to_device(device)?,
        };
        let reward_q = Ensemble::new("reward_q", o + a, &[h, h], 2, &mut noise)?.to_device(device)?;
        let cost_q = Ensemble::new("cost_q", o + a, &[h, h], 2, &mut noise)?.to_device(device)?;
        let reward_v =
            Mlp::pytorch_default("reward_v", &[o, h, h, 1], Activation::Relu, &mut noise)?.to_device(device)?;
        let cost_v = Mlp::pytorch_default("cost_v", &[o, h, h, 1], Activation::Relu, &mut noise)?.to_device(device)?;
        Ok(LspcLearner {
            vae_optim: Adam::new(vae.named_vars(), settings.lr, None)?,
            safety_optim: Adam::new(safety.named_vars(), settings.lr, None)?,
            reward_q_optim: Adam::new(reward_q.named_vars(), settings.lr, None)?,
            cost_q_optim: Adam::new(cost_q.named_vars(), settings.lr, None)?,
            reward_v_optim: Adam::new(reward_v.named_vars(), settings.lr, None)?,
            cost_v_optim: Adam::new(cost_v.named_vars(), settings.lr, None)?,
            reward_q_target: reward_q.copy()?,
            cost_q_target: cost_q.copy()?,
            data: Transitions::new(data, device)?,
            vae,
            safety,
            reward_q,
            cost_q,
            reward_v,
            cost_v,
            noise,
            settings,
        })
    }

    /// The VAE's per-row loss `w·(Σ_d (decode(s, μ + σε) − a)² + β·KL)`, averaged over rows.
    pub fn vae_loss(&self, obs: &Tensor, act: &Tensor, eps: &Tensor, weights: &Tensor) -> anyhow::Result<Tensor> {
        let out = self.vae.forward(obs, act, eps)?;
        let reconstruction = out.reconstruction.sub(act)?.sqr()?.sum(1)?;
        let var = out.std.sqr()?;
        let kl = var
            .log()?
            .affine(1.0, 1.0)?
            .sub(&out.mean.sqr()?)?
            .sub(&var)?
            .mean(1)?
            .affine(-0.5 * self.settings.vae_beta, 0.0)?;
        Ok(weights.mul(&reconstruction.add(&kl)?)?.mean_all()?)
    }

    /// The safety encoder's loss `mean(w·Σ_d (decode(s, max_latent·tanh(μ + σε)) − a)²)`.
    pub fn safety_loss(&self, obs: &Tensor, act: &Tensor, eps: &Tensor, weights: &Tensor) -> anyhow::Result<Tensor> {
        let z = self.safety.latent(obs, eps, self.settings.max_latent)?;
        let action = LatentPolicy::decode(&self.vae.decoder, obs, &z, MAX_ACTION)?;
        Ok(weights.mul(&action.sub(act)?.sqr()?.sum(1)?)?.mean_all()?)
    }

    pub fn update(&mut self, batch: &Batch) -> anyhow::Result<Figures> {
        let s = self.settings.clone();
        let input = concat(&batch.obs, &batch.act)?;
        let continues = batch.done.affine(-s.gamma, s.gamma)?;

        // 1. The backups' next-state values, before any update.
        let next_v = self.reward_v.forward(&batch.next_obs)?.squeeze(1)?.detach();
        let next_vc = self.cost_v.forward(&batch.next_obs)?.squeeze(1)?.relu()?.detach();

        // 2-3. Reward value and pair.
        let q = Ensemble::min(&self.reward_q_target.values(&input)?)?.detach();
        let reward_adv = q.sub(&self.reward_v.forward(&batch.obs)?.squeeze(1)?)?;
        let reward_v_loss = expectile_loss(&reward_adv, s.iql_tau)?;
        self.reward_v_optim.step(&reward_v_loss.backward()?)?;
        let target = batch.reward.add(&continues.mul(&next_v)?)?.detach();
        let reward_q_loss = Ensemble::mean_loss(&self.reward_q.values(&input)?, &target)?;
        self.reward_q_optim.step(&reward_q_loss.backward()?)?;
        soft_update(&self.reward_q_target.named_vars(), &self.reward_q.named_vars(), s.tau)?;

        // 4-5. Cost value (a lower expectile of the pessimistic cost) and pair.
        let qc = Ensemble::max(&self.cost_q_target.values(&input)?)?.relu()?.detach();
        let vc = self.cost_v.forward(&batch.obs)?.squeeze(1)?.relu()?;
        let cost_adv = vc.sub(&qc)?;
        let cost_v_loss = expectile_loss(&cost_adv, s.iql_tau)?;
        self.cost_v_optim.step(&cost_v_loss.backward()?)?;
        let vc = vc.detach();
        let mask = vc
            .lt(s.safe_threshold)?
            .to_dtype(DType::F32)?
            .mul(&qc.lt(s.safe_threshold)?.to_dtype(DType::F32)?)?;
        let target = batch.cost.add(&continues.mul(&next_vc)?)?.detach();
        let cost_q_loss = Ensemble::mean_loss(&self.cost_q.values(&input)?, &target)?;
        self.cost_q_optim.step(&cost_q_loss.backward()?)?;
        soft_update(&self.cost_q_target.named_vars(), &self.cost_q.named_vars(), s.tau)?;

        // 6. The VAE, weighted towards actions cheaper than the state's cost value.
        let rows = batch.obs.dim(0)?;
        let device = batch.obs.device().clone();
        let draw =
            |noise: &mut Noise| Tensor::from_vec(noise.normals_f32(rows * s.latent_dim), (rows, s.latent_dim), &device);
        let cost_w = cost_adv
            .detach()
            .affine(s.beta_cost, 0.0)?
            .exp()?
            .minimum(s.exp_adv_max_cost)?
            .mul(&mask)?;
        let eps = draw(&mut self.noise)?;
        let vae_loss = self.vae_loss(&batch.obs, &batch.act, &eps, &cost_w)?;
        self.vae_optim.step(&vae_loss.backward()?)?;

        // 7. The safety encoder, weighted towards actions of high reward advantage, through the updated decoder.
        let reward_w = reward_adv
            .detach()
            .affine(s.beta_reward, 0.0)?
            .exp()?
            .minimum(s.exp_adv_max_reward)?;
        let eps = draw(&mut self.noise)?;
        let safety_loss = self.safety_loss(&batch.obs, &batch.act, &eps, &reward_w)?;
        self.safety_optim.step(&safety_loss.backward()?)?;

        let scalar = |t: &Tensor| -> anyhow::Result<f64> { Ok(f64::from(t.to_scalar::<f32>()?)) };
        Ok(vec![
            ("reward_v", scalar(&reward_v_loss)?),
            ("reward_q", scalar(&reward_q_loss)?),
            ("cost_v", scalar(&cost_v_loss)?),
            ("cost_q", scalar(&cost_q_loss)?),
            ("vae", scalar(&vae_loss)?),
            ("safety", scalar(&safety_loss)?),
        ])
    }
}

impl EveryThresholdLearner for LspcLearner {
    fn step(&mut self) -> anyhow::Result<Figures> {
        let s = &self.settings;
        let batch = self.data.sample(s.batch_size, 1.0, 1.0, &mut self.noise)?;
        self.update(&batch)
    }

    /// Writes the evaluator's `latent_policy` checkpoint (decoder and safety encoder: LSPC-O, one model for every
    /// threshold) with `training` recorded.
    fn write(&self, dir: &Path, task: &str, training: serde_json::Value) -> anyhow::Result<()> {
        let s = &self.settings;
        let config = PolicyConfig {
            format: checkpoint::FORMAT.into(),
            task: task.to_owned(),
            obs_dim: self.safety.trunk.input_dim(),
            act_dim: self.vae.decoder.output_dim(),
            architecture: Architecture::LatentPolicy {
                hidden_sizes: vec![s.hidden, s.hidden],
                decoder_hidden_sizes: vec![s.hidden, s.hidden],
                latent_dim: s.latent_dim,
                max_latent: s.max_latent,
                latent: LatentSource::SafetyEncoder,
                max_action: MAX_ACTION,
            },
            observation_normalization: None,
            conditioning: Conditioning::Unconditioned,
            training: Some(training),
        };
        let mut tensors = dsrl_policy::tensors_of(self.safety.named_vars());
        tensors.extend(dsrl_policy::tensors_of(self.vae.decoder.named_vars()));
        checkpoint::write(dir, &config, &tensors)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::offline::tests::{assert_falls, first_weights, read_back, run_steps, toy};

    fn small(seed: u64) -> LspcSettings {
        LspcSettings {
            hidden: 16,
            latent_dim: 3,
            batch_size: 64,
            lr: 3e-3,
            seed,
            ..LspcSettings::default()
        }
    }

    #[test]
    fn the_losses_are_the_weighted_sums_worked_by_hand() {
        let learner = LspcLearner::new(small(1), &toy()).unwrap();
        let cpu = &dsrl_policy::Device::Cpu;
        let obs = Tensor::new(&[[0.2f32, 0.4], [0.6, 0.1]], cpu).unwrap();
        let act = Tensor::new(&[[0.1f32], [-0.3]], cpu).unwrap();
        let eps = Tensor::new(&[[0.5f32, -1.0, 0.2], [0.0, 1.5, -0.4]], cpu).unwrap();
        let weights = Tensor::new(&[2.0f32, 0.5], cpu).unwrap();

        // The VAE: per row, the squared error of the decoded posterior draw plus β·KL (a mean over latents).
        let got = learner
            .vae_loss(&obs, &act, &eps, &weights)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        let (mean, std) = learner.vae.encode(&obs, &act).unwrap();
        let z = mean.add(&std.mul(&eps).unwrap()).unwrap();
        let decoded = learner.vae.decode(&obs, &z).unwrap().to_vec2::<f32>().unwrap();
        let (mean, std) = (mean.to_vec2::<f32>().unwrap(), std.to_vec2::<f32>().unwrap());
        let mut want = 0.0f64;
        for r in 0..2 {
            let error = (f64::from(decoded[r][0]) - [0.1, -0.3][r]).powi(2);
            let kl = -0.5
                * (0..3)
                    .map(|j| {
                        let (m, s) = (f64::from(mean[r][j]), f64::from(std[r][j]));
                        1.0 + (s * s).ln() - m * m - s * s
                    })
                    .sum::<f64>()
                / 3.0;
            want += [2.0, 0.5][r] * (error + 0.5 * kl) / 2.0;
        }
        assert!((f64::from(got) - want).abs() < 1e-5, "{got} vs {want}");

        // The safety encoder: the decoded squashed latent's squared error.
        let got = learner
            .safety_loss(&obs, &act, &eps, &weights)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        let (mu, log_std) = learner.safety.forward(&obs).unwrap();
        let z = mu
            .add(&log_std.exp().unwrap().mul(&eps).unwrap())
            .unwrap()
            .tanh()
            .unwrap()
            .affine(0.25, 0.0)
            .unwrap();
        let decoded = learner.vae.decode(&obs, &z).unwrap().to_vec2::<f32>().unwrap();
        let want: f64 = (0..2)
            .map(|r| [2.0, 0.5][r] * (f64::from(decoded[r][0]) - [0.1, -0.3][r]).powi(2) / 2.0)
            .sum();
        assert!((f64::from(got) - want).abs() < 1e-5, "{got} vs {want}");
    }

    #[test]
    fn a_few_steps_train_deterministically_and_the_checkpoint_decodes_the_encoders_latent() {
        let data = toy();
        let mut learner = LspcLearner::new(small(3), &data).unwrap();
        let (first, last) = run_steps(|| learner.step(), 100);
        assert_falls(&first, &last, &["reward_q", "safety"]);
        let mut again = LspcLearner::new(small(3), &data).unwrap();
        for _ in 0..100 {
            again.step().unwrap();
        }
        assert_eq!(
            first_weights(learner.safety.named_vars()),
            first_weights(again.safety.named_vars())
        );

        let (config, tensors, policy) = read_back(&learner, 100);
        let mut rollout = policy.rollout(20.0, 1).unwrap();
        rollout.start_episode(0, 5).unwrap();
        let action = rollout.act(&[0], &[0.3, 0.7]).unwrap();
        // By hand: the episode generator's first draws as ε.
        let cpu = &dsrl_policy::Device::Cpu;
        let eps = Tensor::from_vec(Noise::seeded(5).normals_f32(3), (1, 3), cpu).unwrap();
        let obs = Tensor::new(&[[0.3f32, 0.7]], cpu).unwrap();
        let z = learner.safety.latent(&obs, &eps, 0.25).unwrap();
        let want = learner.vae.decode(&obs, &z).unwrap().to_vec2::<f32>().unwrap()[0][0];
        assert!((action[0] - want).abs() < 1e-5, "{action:?} vs {want}");
        // The prior mode reads the same file without the safety encoder.
        let mut prior = config.clone();
        if let Architecture::LatentPolicy { latent, .. } = &mut prior.architecture {
            *latent = LatentSource::Prior;
        }
        let policy = dsrl_policy::Policy::load(&prior, &tensors).unwrap();
        let mut rollout = policy.rollout(20.0, 1).unwrap();
        rollout.start_episode(0, 5).unwrap();
        let z = eps.clamp(-0.25f32, 0.25f32).unwrap();
        let want = learner.vae.decode(&obs, &z).unwrap().to_vec2::<f32>().unwrap()[0][0];
        assert!((rollout.act(&[0], &[0.3, 0.7]).unwrap()[0] - want).abs() < 1e-5);
    }
}
