//! BCQ-Lag (OSRL `bcql.py`, spec 5.6): batch-constrained Q-learning with a Lagrangian cost constraint.
//!
//! A VAE models the dataset's actions; a perturbation actor nudges a decoded action by at most φ·max_action
//! towards higher reward-Q; reward and cost critics are double ensembles (2 + 2 networks each) with target copies;
//! a PID controller sets λ from the cost-Q of the actor's actions against the per-step threshold. One training step
//! is, in OSRL's order: VAE → reward critic → cost critic → actor → soft updates (τ = 0.005).
//!
//! The trained actor is written as the evaluator's `bcq_actor` (`actor.pi.<i>` + `vae.decoder.<i>`).

use std::path::Path;

use dsrl_policy::adam::Adam;
use dsrl_policy::checkpoint::{self, Architecture, Conditioning, PolicyConfig};
use dsrl_policy::mlp::{Activation, Mlp, layer_sizes};
use dsrl_policy::noise::Noise;
use dsrl_policy::offline::{DoubleCritic, Ensemble, PidLagrangian, qc_threshold, repeat_rows, soft_update};
use dsrl_policy::vae::Vae;
use dsrl_policy::{Device, Tensor, Var};

use crate::offline::{Batch, Figures, ThresholdLearner, Transitions};
use crate::{Demonstrations, MAX_ACTION};

/// OSRL's BCQ-L configuration (spec 5.6).
#[derive(Debug, Clone, PartialEq)]
pub struct BcqlSettings {
    pub hidden_sizes: Vec<usize>,
    pub vae_hidden: usize,
    pub num_q: usize,
    pub gamma: f64,
    pub tau: f64,
    pub phi: f64,
    pub beta: f64,
    /// Weight of the smaller of the two ensembles' values in the target (`0.75·min + 0.25·max`).
    pub lmbda: f64,
    pub sample_action_num: usize,
    pub lr: f64,
    pub reward_scale: f64,
    pub cost_scale: f64,
    pub batch_size: usize,
    pub steps: u64,
    pub pid: (f64, f64, f64),
    pub seed: u64,
}

impl Default for BcqlSettings {
    fn default() -> Self {
        BcqlSettings {
            hidden_sizes: vec![256, 256],
            vae_hidden: 400,
            num_q: 2,
            gamma: 0.99,
            tau: 0.005,
            phi: 0.05,
            beta: 0.5,
            lmbda: 0.75,
            sample_action_num: 10,
            lr: 1e-3,
            reward_scale: 0.1,
            cost_scale: 1.0,
            batch_size: 512,
            steps: 100_000,
            pid: (0.1, 0.003, 0.001),
            seed: 0,
        }
    }
}

pub struct BcqlLearner {
    pub settings: BcqlSettings,
    pub vae: Vae,
    pub actor: Mlp,
    actor_target: Mlp,
    critic: DoubleCritic,
    critic_target: DoubleCritic,
    cost_critic: DoubleCritic,
    cost_critic_target: DoubleCritic,
    vae_optim: Adam,
    actor_optim: Adam,
    critic_optim: Adam,
    cost_critic_optim: Adam,
    pid: PidLagrangian,
    noise: Noise,
    data: Transitions,
    obs_dim: usize,
    act_dim: usize,
}

impl BcqlLearner {
    /// A learner for the cost threshold `kappa` of a task whose episodes last `episode_len` steps, on the CPU.
    pub fn new(settings: BcqlSettings, data: &Demonstrations, kappa: f64, episode_len: usize) -> anyhow::Result<Self> {
        Self::on_device(settings, data, kappa, episode_len, &Device::Cpu)
    }

    /// As [`BcqlLearner::new`], training on `device` (networks initialised on the CPU from the seed, then moved).
    pub fn on_device(
        settings: BcqlSettings,
        data: &Demonstrations,
        kappa: f64,
        episode_len: usize,
        device: &Device,
    ) -> anyhow::Result<Self> {
        let (o, a) = (data.obs_dim, data.act_dim);
        let mut noise = Noise::seeded(settings.seed);
        let vae = Vae::new(o, a, settings.vae_hidden, 2 * a, MAX_ACTION, &mut noise)?.to_device(device)?;
        let actor = Mlp::pytorch_default(
            "actor.pi",
            &layer_sizes(o + a, &settings.hidden_sizes, a),
            Activation::Tanh,
            &mut noise,
        )?
        .to_device(device)?;
        let critic = DoubleCritic::new("critic", o + a, &settings.hidden_sizes, settings.num_q, &mut noise)?
            .to_device(device)?;
        let cost_critic = DoubleCritic::new("cost_critic", o + a, &settings.hidden_sizes, settings.num_q, &mut noise)?
            .to_device(device)?;
        let (kp, ki, kd) = settings.pid;
        let threshold = qc_threshold(kappa, settings.gamma, episode_len);
        Ok(BcqlLearner {
            vae_optim: Adam::new(vae.named_vars(), settings.lr, None)?,
            actor_optim: Adam::new(actor.named_vars(), settings.lr, None)?,
            critic_optim: Adam::new(critic.named_vars(), settings.lr, None)?,
            cost_critic_optim: Adam::new(cost_critic.named_vars(), settings.lr, None)?,
            actor_target: actor.copy()?,
            critic_target: critic.copy()?,
            cost_critic_target: cost_critic.copy()?,
            pid: PidLagrangian::new(kp, ki, kd, threshold),
            vae,
            actor,
            critic,
            cost_critic,
            noise,
            data: Transitions::new(data, device)?,
            obs_dim: o,
            act_dim: a,
            settings,
        })
    }

    /// `clamp(action + φ·max_action·tanh(actor([obs, action])), ±max_action)`.
    fn perturb(&self, actor: &Mlp, obs: &Tensor, action: &Tensor) -> anyhow::Result<Tensor> {
        let nudge = actor
            .forward(&Tensor::cat(&[obs, action], 1)?)?
            .tanh()?
            .affine(self.settings.phi * MAX_ACTION, 0.0)?;
        Ok(action.add(&nudge)?.clamp(-MAX_ACTION, MAX_ACTION)?)
    }

    /// Standard normal draws `[rows, latent]`, clipped to ±0.5 (OSRL's `decode` without a latent).
    fn latents(&mut self, rows: usize) -> anyhow::Result<Tensor> {
        let latent = self.vae.latent_dim;
        let values: Vec<f32> = (0..rows * latent)
            .map(|_| {
                self.noise
                    .normal()
                    .clamp(-dsrl_policy::bcq::LATENT_CLIP, dsrl_policy::bcq::LATENT_CLIP) as f32
            })
            .collect();
        Ok(Tensor::from_vec(values, (rows, latent), self.data.device())?)
    }
}

impl ThresholdLearner for BcqlLearner {
    /// One training step on a uniformly drawn batch (with replacement, as OSRL's `TransitionDataset`).
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
        let b = batch.obs.dim(0)?;
        let (obs, next_obs, act) = (&batch.obs, &batch.next_obs, &batch.act);
        let (reward, cost, done) = (&batch.reward, &batch.cost, &batch.done);
        let mut stats = Vec::new();

        // VAE.
        let eps_values = self.noise.normals_f32(b * self.vae.latent_dim);
        let eps = Tensor::from_vec(eps_values, (b, self.vae.latent_dim), self.data.device())?;
        let out = self.vae.forward(obs, act, &eps)?;
        let (loss, _, _) = Vae::loss(&out, act, self.settings.beta)?;
        stats.push(("vae", f64::from(loss.to_scalar::<f32>()?)));
        self.vae_optim.step(&loss.backward()?)?;

        // Targets: each next state repeated `n` times with a perturbed decoded action.
        let n = self.settings.sample_action_num;
        let next_rep = repeat_rows(next_obs, n)?;
        let z = self.latents(b * n)?;
        let decoded = self.vae.decode(&next_rep, &z)?.detach();
        let next_act = self.perturb(&self.actor_target, &next_rep, &decoded)?.detach();
        let next_input = Tensor::cat(&[&next_rep, &next_act], 1)?;
        let lmbda = self.settings.lmbda;
        let mix = |q1: &Tensor, q2: &Tensor| DoubleCritic::soft_clipped_max(q1, q2, lmbda, n);
        let gamma = self.settings.gamma;
        let (_, t1, t2) = self.critic_target.predict(&next_input)?;
        let target_q = reward.add(&done.affine(-gamma, gamma)?.mul(&mix(&t1, &t2)?)?)?.detach();
        let (_, c1, c2) = self.cost_critic_target.predict(&next_input)?;
        // OSRL's cost target has no (1 − done).
        let target_qc = cost.add(&mix(&c1, &c2)?.affine(gamma, 0.0)?)?.detach();

        let input = Tensor::cat(&[obs, act], 1)?;
        let (values, _, _) = self.critic.predict(&input)?;
        let loss = Ensemble::loss(&values, &target_q)?;
        stats.push(("critic", f64::from(loss.to_scalar::<f32>()?)));
        self.critic_optim.step(&loss.backward()?)?;
        let (values, _, _) = self.cost_critic.predict(&input)?;
        let loss = Ensemble::loss(&values, &target_qc)?;
        stats.push(("cost_critic", f64::from(loss.to_scalar::<f32>()?)));
        self.cost_critic_optim.step(&loss.backward()?)?;

        // Actor.
        let z = self.latents(b)?;
        let decoded = self.vae.decode(obs, &z)?.detach();
        let action = self.perturb(&self.actor, obs, &decoded)?;
        let input = Tensor::cat(&[obs, &action], 1)?;
        let (_, q1, q2) = self.critic.predict(&input)?;
        let (_, qc1, qc2) = self.cost_critic.predict(&input)?;
        let qc = qc1.minimum(&qc2)?;
        let lagrangian = self.pid.control(&qc.detach().to_vec1::<f32>()?);
        let loss = q1.minimum(&q2)?.mean_all()?.neg()?.add(
            &qc.affine(1.0, -self.pid.threshold)?
                .affine(lagrangian, 0.0)?
                .mean_all()?,
        )?;
        stats.push(("actor", f64::from(loss.to_scalar::<f32>()?)));
        stats.push(("lagrangian", lagrangian));
        self.actor_optim.step(&loss.backward()?)?;

        let tau = self.settings.tau;
        soft_update(&self.critic_target.named_vars(), &self.critic.named_vars(), tau)?;
        soft_update(
            &self.cost_critic_target.named_vars(),
            &self.cost_critic.named_vars(),
            tau,
        )?;
        soft_update(&self.actor_target.named_vars(), &self.actor.named_vars(), tau)?;
        Ok(stats)
    }

    /// Writes the actor and the VAE's decoder as a per-threshold `bcq_actor` policy.
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
        let config = PolicyConfig {
            format: checkpoint::FORMAT.into(),
            task: task.to_owned(),
            obs_dim: self.obs_dim,
            act_dim: self.act_dim,
            architecture: Architecture::BcqActor {
                hidden_sizes: self.settings.hidden_sizes.clone(),
                activation: Activation::Tanh,
                decoder_hidden_sizes: vec![self.settings.vae_hidden; 2],
                latent_dim: self.vae.latent_dim,
                phi: self.settings.phi,
                max_action: MAX_ACTION,
            },
            observation_normalization: None,
            conditioning: Conditioning::PerThreshold { cost_threshold: kappa },
            training: Some(training),
        };
        let vars: Vec<(String, Var)> = self
            .actor
            .named_vars()
            .into_iter()
            .chain(self.vae.decoder.named_vars())
            .collect();
        checkpoint::write(dir, &config, &dsrl_policy::tensors_of(vars))?;
        Ok(())
    }
}

impl BcqlLearner {
    /// The actor's action for `obs` rows with the given latents (what the evaluator computes).
    pub fn act(&self, obs: &Tensor, z: &Tensor) -> anyhow::Result<Tensor> {
        let decoded = self.vae.decode(obs, z)?;
        self.perturb(&self.actor, obs, &decoded)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::offline::tests::{figure, first_weights, run, toy};

    fn small(seed: u64) -> BcqlSettings {
        BcqlSettings {
            hidden_sizes: vec![16, 16],
            vae_hidden: 16,
            batch_size: 32,
            steps: 60,
            seed,
            ..BcqlSettings::default()
        }
    }

    #[test]
    fn a_few_steps_train_every_part_deterministically_and_write_what_the_evaluator_plays() {
        let data = toy();
        let mut learner = BcqlLearner::new(small(3), &data, 2.0, 10).unwrap();
        // κ = 2 over 10 steps with γ = 0.99: the per-step threshold (~1.9).
        assert!((learner.qc_threshold() - 2.0 * (1.0 - 0.99f64.powi(10)) / 0.01 / 10.0).abs() < 1e-12);
        let (first, last) = run(&mut learner, 60);
        assert!(figure(&last, "vae") < figure(&first, "vae"), "{first:?} -> {last:?}");
        // Half the data costs 1 per step (a discounted cost value up to ~9.6), over the per-step threshold of ~1.9:
        // λ rises.
        assert!(figure(&last, "lagrangian") > 0.0, "{last:?}");

        // The same seed gives the same weights.
        let mut again = BcqlLearner::new(small(3), &data, 2.0, 10).unwrap();
        run(&mut again, 60);
        assert_eq!(
            first_weights(learner.actor.named_vars()),
            first_weights(again.actor.named_vars())
        );

        // The written checkpoint is an evaluator bcq_actor that acts like the learner.
        let dir = tempfile::tempdir().unwrap();
        learner
            .write(dir.path(), "toy", 10.0, serde_json::json!({"steps": 60}))
            .unwrap();
        let (config, tensors) = checkpoint::read(dir.path()).unwrap();
        assert_eq!(config.architecture.name(), "bcq_actor");
        assert!(matches!(config.conditioning, Conditioning::PerThreshold { cost_threshold } if cost_threshold == 10.0));
        let policy = dsrl_policy::Policy::load(&config, &tensors).unwrap();
        let mut rollout = policy.rollout(10.0, 1).unwrap();
        rollout.start_episode(0, 42).unwrap();
        let obs = [0.3f32, 0.7];
        let played = rollout.act(&[0], &obs).unwrap();
        // The evaluator draws the latent from a generator seeded with the episode seed.
        let mut g = Noise::seeded(42);
        let z: Vec<f32> = (0..2).map(|_| g.normal().clamp(-0.5, 0.5) as f32).collect();
        let z = Tensor::from_vec(z, (1, 2), &Device::Cpu).unwrap();
        let o = Tensor::from_vec(obs.to_vec(), (1, 2), &Device::Cpu).unwrap();
        let mine: Vec<f32> = learner.act(&o, &z).unwrap().flatten_all().unwrap().to_vec1().unwrap();
        assert!((mine[0] - played[0]).abs() < 1e-6, "{mine:?} vs {played:?}");
    }
}
