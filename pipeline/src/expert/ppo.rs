//! The PPO-Lagrangian learner: a [`GaussianActor`], reward and cost critics, and the PID Lagrange multiplier that
//! weighs the cost advantage. One `update` per collect: GAE on both signals, then `repeat_per_collect` passes of
//! clipped-surrogate minibatch steps on the mixed advantage `(A_r − λ·A_c) / (1 + λ)` and MSE steps on the critics.

use std::collections::HashMap;

use anyhow::Context;
use dsrl_policy::adam::Adam;
use dsrl_policy::checkpoint::{self, Architecture, ObservationNormalization, PolicyConfig};
use dsrl_policy::gaussian::{GaussianActor, matrix};
use dsrl_policy::mlp::{Activation, Mlp};
use dsrl_policy::noise::Noise;
use dsrl_policy::{Device, Tensor};
use serde::{Deserialize, Serialize};

use super::advantage::{StepValue, gae, normalize};
use super::lagrangian::PidLagrangian;
use super::normalization::ObservationStats;
use crate::recipe::ExpertSettings;

const ACTIVATION: Activation = Activation::Tanh;

/// The steps of one collect, episode after episode (each episode's steps contiguous and in order).
#[derive(Debug, Default, Clone)]
pub struct Rollout {
    pub obs_dim: usize,
    pub act_dim: usize,
    pub observations: Vec<f32>,
    pub next_observations: Vec<f32>,
    /// The sampled (unclipped) actions the log-probabilities refer to.
    pub actions: Vec<f32>,
    pub log_probs: Vec<f32>,
    pub rewards: Vec<f64>,
    pub costs: Vec<f64>,
    pub terminated: Vec<bool>,
    pub episode_end: Vec<bool>,
}

impl Rollout {
    pub fn len(&self) -> usize {
        self.rewards.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rewards.is_empty()
    }
}

/// What one update did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct UpdateStats {
    pub lagrangian: f64,
    pub actor_loss: f64,
    pub critic_loss: f64,
    /// Mean of `log π_old − log π_new` over the last pass.
    pub approx_kl: f64,
    pub std: f64,
}

pub struct Learner {
    pub actor: GaussianActor,
    reward_critic: Mlp,
    cost_critic: Mlp,
    actor_opt: Adam,
    critic_opt: Adam,
    pub lagrangian: PidLagrangian,
    /// The running observation statistics the networks see their inputs through, when the recipe asks for them.
    observation_stats: Option<ObservationStats>,
    settings: ExpertSettings,
}

/// What, besides the tensors, a training checkpoint needs to rebuild the learner.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LearnerState {
    pub lagrangian: PidLagrangian,
    pub actor_steps: u64,
    pub critic_steps: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observation_stats: Option<ObservationStats>,
}

impl Learner {
    pub fn new(
        settings: &ExpertSettings,
        obs_dim: usize,
        act_dim: usize,
        max_action: f64,
        noise: &mut Noise,
    ) -> anyhow::Result<Learner> {
        let actor = GaussianActor::new(obs_dim, act_dim, &settings.hidden_sizes, ACTIVATION, max_action, noise)?;
        let sizes: Vec<usize> = std::iter::once(obs_dim)
            .chain(settings.hidden_sizes.iter().copied())
            .chain([1])
            .collect();
        let reward_critic = Mlp::orthogonal("critic.reward", &sizes, ACTIVATION, 1.0, 1.0, noise)?;
        let cost_critic = Mlp::orthogonal("critic.cost", &sizes, ACTIVATION, 1.0, 1.0, noise)?;
        let clip = Some(settings.max_grad_norm);
        let actor_opt = Adam::new(actor.named_vars(), settings.lr, clip)?;
        let mut critic_vars = reward_critic.named_vars();
        critic_vars.extend(cost_critic.named_vars());
        let critic_opt = Adam::new(critic_vars, settings.lr, clip)?;
        let gains = settings.lagrangian;
        Ok(Learner {
            actor,
            reward_critic,
            cost_critic,
            actor_opt,
            critic_opt,
            lagrangian: PidLagrangian::new(gains.kp, gains.ki, gains.kd),
            observation_stats: settings
                .observation_normalization
                .then(|| ObservationStats::new(obs_dim)),
            settings: settings.clone(),
        })
    }

    /// Every tensor of the training state: networks and optimizer moments.
    pub fn tensors(&self) -> Vec<(String, Tensor)> {
        let mut out = dsrl_policy::tensors_of(
            self.actor
                .named_vars()
                .into_iter()
                .chain(self.reward_critic.named_vars())
                .chain(self.cost_critic.named_vars()),
        );
        out.extend(self.actor_opt.state("adam.actor"));
        out.extend(self.critic_opt.state("adam.critic"));
        out
    }

    pub fn state(&self) -> LearnerState {
        LearnerState {
            lagrangian: self.lagrangian.clone(),
            actor_steps: self.actor_opt.steps(),
            critic_steps: self.critic_opt.steps(),
            observation_stats: self.observation_stats.clone(),
        }
    }

    /// Rebuilds a learner from [`Learner::tensors`] and [`Learner::state`].
    pub fn restore(
        settings: &ExpertSettings,
        max_action: f64,
        tensors: &HashMap<String, Tensor>,
        state: &LearnerState,
    ) -> anyhow::Result<Learner> {
        anyhow::ensure!(
            settings.observation_normalization == state.observation_stats.is_some(),
            "the saved expert was trained {} observation normalization but the recipe now says \
             observation_normalization = {}: resume with the recipe it started with, or start a new state folder",
            if state.observation_stats.is_some() {
                "with"
            } else {
                "without"
            },
            settings.observation_normalization
        );
        let mean_net = Mlp::from_tensors("actor.mu", tensors, ACTIVATION)?;
        let log_std = tensors.get("actor.log_std").context("actor.log_std is missing")?;
        let actor = GaussianActor {
            mean_net,
            log_std: dsrl_policy::Var::from_tensor(&log_std.copy()?)?,
            max_action,
        };
        let reward_critic = Mlp::from_tensors("critic.reward", tensors, ACTIVATION)?;
        let cost_critic = Mlp::from_tensors("critic.cost", tensors, ACTIVATION)?;
        let clip = Some(settings.max_grad_norm);
        let mut actor_opt = Adam::new(actor.named_vars(), settings.lr, clip)?;
        actor_opt.restore("adam.actor", tensors, state.actor_steps)?;
        let mut critic_vars = reward_critic.named_vars();
        critic_vars.extend(cost_critic.named_vars());
        let mut critic_opt = Adam::new(critic_vars, settings.lr, clip)?;
        critic_opt.restore("adam.critic", tensors, state.critic_steps)?;
        Ok(Learner {
            actor,
            reward_critic,
            cost_critic,
            actor_opt,
            critic_opt,
            lagrangian: state.lagrangian.clone(),
            observation_stats: state.observation_stats.clone(),
            settings: settings.clone(),
        })
    }

    /// The actor alone, in the evaluator's checkpoint format.
    pub fn write_policy(&self, dir: &std::path::Path, task: &str) -> anyhow::Result<()> {
        let config = PolicyConfig {
            format: checkpoint::FORMAT.into(),
            task: task.to_owned(),
            obs_dim: self.actor.mean_net.input_dim(),
            act_dim: self.actor.mean_net.output_dim(),
            architecture: Architecture::GaussianMlp {
                hidden_sizes: self.settings.hidden_sizes.clone(),
                activation: ACTIVATION,
                max_action: self.actor.max_action,
            },
            observation_normalization: self.observation_stats.as_ref().map(|stats| {
                let (mean, std) = stats.mean_and_std();
                ObservationNormalization { mean, std }
            }),
            conditioning: checkpoint::Conditioning::Unconditioned,
            training: Some(serde_json::json!({ "by": "dsrl-admin collect (PPO-Lagrangian expert)" })),
        };
        checkpoint::write(dir, &config, &dsrl_policy::tensors_of(self.actor.named_vars()))?;
        Ok(())
    }

    /// What the networks see of raw observations: normalized when the recipe asks for it.
    fn inputs<'a>(&self, observations: &'a [f32]) -> std::borrow::Cow<'a, [f32]> {
        match &self.observation_stats {
            Some(stats) => std::borrow::Cow::Owned(stats.apply(observations)),
            None => std::borrow::Cow::Borrowed(observations),
        }
    }

    /// Sampled actions and their log-probabilities for `[n, obs_dim]` observations.
    pub fn act(&self, observations: &[f32], n: usize, noise: &mut Noise) -> anyhow::Result<(Vec<f32>, Vec<f32>)> {
        let obs = matrix(&self.inputs(observations), n, self.actor.mean_net.input_dim())?;
        Ok(self.actor.sample_with_log_prob(&obs, noise)?)
    }

    /// A critic's values of `[n, obs_dim]` network inputs (already normalized where the recipe asks for it).
    fn values(critic: &Mlp, inputs: &[f32], n: usize, obs_dim: usize) -> anyhow::Result<Vec<f64>> {
        let v = critic
            .forward(&matrix(inputs, n, obs_dim)?)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        Ok(v.into_iter().map(f64::from).collect())
    }

    /// One PPO-Lagrangian update from a collect: first λ from the collect's episode costs against `cost_limit`;
    /// last, the observation statistics (if any) take in the collect's observations.
    pub fn update(
        &mut self,
        rollout: &Rollout,
        episode_costs: &[f64],
        cost_limit: f64,
        noise: &mut Noise,
    ) -> anyhow::Result<UpdateStats> {
        let lagrangian = self.lagrangian.step(episode_costs, cost_limit);
        let (n, od, ad) = (rollout.len(), rollout.obs_dim, rollout.act_dim);
        anyhow::ensure!(n > 0, "an update needs steps");
        let s = &self.settings;
        // Normalized once for both critics and the actor, with the statistics the collect was played with.
        let inputs = self.inputs(&rollout.observations);
        let next_inputs = self.inputs(&rollout.next_observations);
        let advantages = |critic: &Mlp, signal: &[f64]| -> anyhow::Result<(Vec<f64>, Vec<f64>)> {
            let values = Self::values(critic, &inputs, n, od)?;
            let next = Self::values(critic, &next_inputs, n, od)?;
            let steps: Vec<StepValue> = (0..n)
                .map(|t| StepValue {
                    signal: signal[t],
                    value: values[t],
                    next_value: next[t],
                    terminated: rollout.terminated[t],
                    episode_end: rollout.episode_end[t],
                })
                .collect();
            Ok(gae(&steps, s.gamma, s.gae_lambda))
        };
        let (mut adv_r, target_r) = advantages(&self.reward_critic, &rollout.rewards)?;
        let (mut adv_c, target_c) = advantages(&self.cost_critic, &rollout.costs)?;
        normalize(&mut adv_r);
        normalize(&mut adv_c);
        let mixed: Vec<f32> = adv_r
            .iter()
            .zip(&adv_c)
            .map(|(r, c)| self.lagrangian.mix(*r, *c) as f32)
            .collect();
        let dev = &Device::Cpu;
        let obs = matrix(&inputs, n, od)?;
        let actions = matrix(&rollout.actions, n, ad)?;
        let old_log_probs = Tensor::from_slice(&rollout.log_probs, n, dev)?;
        let mixed = Tensor::from_slice(&mixed, n, dev)?;
        let to_f32 = |v: &[f64]| v.iter().map(|x| *x as f32).collect::<Vec<f32>>();
        let target_r = Tensor::from_slice(&to_f32(&target_r), n, dev)?;
        let target_c = Tensor::from_slice(&to_f32(&target_c), n, dev)?;

        let mut stats = UpdateStats {
            lagrangian,
            ..UpdateStats::default()
        };
        for pass in 0..s.repeat_per_collect {
            let order = noise.permutation(n);
            let (mut kl_sum, mut actor_sum, mut critic_sum, mut batches) = (0.0, 0.0, 0.0, 0);
            for chunk in order.chunks(s.minibatch_size) {
                let idx = Tensor::from_slice(chunk, chunk.len(), dev)?;
                let obs_b = obs.index_select(&idx, 0)?;
                let log_probs = self.actor.log_prob(&obs_b, &actions.index_select(&idx, 0)?)?;
                let old_b = old_log_probs.index_select(&idx, 0)?;
                let adv_b = mixed.index_select(&idx, 0)?;
                let ratio = log_probs.sub(&old_b)?.exp()?;
                let clipped = ratio.clamp(1.0 - s.clip_ratio, 1.0 + s.clip_ratio)?;
                let surrogate = ratio.mul(&adv_b)?.minimum(&clipped.mul(&adv_b)?)?;
                let actor_loss = surrogate.mean_all()?.neg()?;
                self.actor_opt.step(&actor_loss.backward()?)?;

                let value_loss = |critic: &Mlp, target: &Tensor| -> anyhow::Result<Tensor> {
                    let v = critic.forward(&obs_b)?.flatten_all()?;
                    Ok(v.sub(&target.index_select(&idx, 0)?)?.sqr()?.mean_all()?)
                };
                let critic_loss =
                    value_loss(&self.reward_critic, &target_r)?.add(&value_loss(&self.cost_critic, &target_c)?)?;
                self.critic_opt.step(&critic_loss.backward()?)?;

                if pass + 1 == s.repeat_per_collect {
                    kl_sum += f64::from(old_b.sub(&log_probs)?.mean_all()?.to_scalar::<f32>()?);
                }
                actor_sum += f64::from(actor_loss.to_scalar::<f32>()?);
                critic_sum += f64::from(critic_loss.to_scalar::<f32>()?);
                batches += 1;
            }
            stats.actor_loss = actor_sum / f64::from(batches);
            stats.critic_loss = critic_sum / f64::from(batches);
            stats.approx_kl = kl_sum / f64::from(batches);
        }
        stats.std = f64::from(self.actor.log_std.as_tensor().exp()?.mean_all()?.to_scalar::<f32>()?);
        if let Some(observation_stats) = &mut self.observation_stats {
            observation_stats.observe(&rollout.observations);
        }
        Ok(stats)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recipe::Recipe;

    fn settings() -> ExpertSettings {
        let mut s = Recipe::load(&Recipe::committed_path("OfflineBallRun-v0"))
            .unwrap()
            .expert
            .unwrap();
        s.hidden_sizes = vec![16, 16];
        s.minibatch_size = 64;
        s.lr = 3e-3;
        s
    }

    /// One-step episodes with reward `1 − (a − 0.5)²` and cost `cost(a)`, whatever the observation (0, or with
    /// `spread` −2, 0, 2 in turn, to give the observation statistics something to learn).
    fn bandit(learner: &Learner, noise: &mut Noise, n: usize, cost: impl Fn(f32) -> f64) -> (Rollout, Vec<f64>) {
        bandit_from(learner, noise, n, cost, false)
    }

    fn bandit_from(
        learner: &Learner,
        noise: &mut Noise,
        n: usize,
        cost: impl Fn(f32) -> f64,
        spread: bool,
    ) -> (Rollout, Vec<f64>) {
        let obs: Vec<f32> = (0..n)
            .map(|i| if spread { 2.0 * (i % 3) as f32 - 2.0 } else { 0.0 })
            .collect();
        let (actions, log_probs) = learner.act(&obs, n, noise).unwrap();
        let costs: Vec<f64> = actions.iter().map(|&a| cost(a)).collect();
        let rollout = Rollout {
            obs_dim: 1,
            act_dim: 1,
            observations: obs.clone(),
            next_observations: obs,
            rewards: actions.iter().map(|&a| 1.0 - f64::from(a - 0.5).powi(2)).collect(),
            costs: costs.clone(),
            actions,
            log_probs,
            terminated: vec![true; n],
            episode_end: vec![true; n],
        };
        (rollout, costs)
    }

    /// The deterministic action at observation 0.5.
    fn mean_action(learner: &Learner) -> f32 {
        learner
            .actor
            .mean(&matrix(&learner.inputs(&[0.5]), 1, 1).unwrap())
            .unwrap()
            .to_vec2::<f32>()
            .unwrap()[0][0]
    }

    #[test]
    fn ppo_moves_the_policy_toward_the_rewarding_action_and_the_lagrangian_holds_it_back() {
        let run = |cost_limit: f64| {
            let mut noise = Noise::seeded(1);
            let mut learner = Learner::new(&settings(), 1, 1, 1.0, &mut noise).unwrap();
            let start = mean_action(&learner);
            // Cost grows with the action (on the scale of episode costs); a limit of 2 is only met by actions near
            // or below 0.1.
            for _ in 0..40 {
                let (rollout, costs) = bandit(&learner, &mut noise, 256, |a| 20.0 * f64::from(a.max(0.0)));
                learner.update(&rollout, &costs, cost_limit, &mut noise).unwrap();
            }
            (start, mean_action(&learner), learner.lagrangian.lagrangian)
        };
        let (start, free, free_lambda) = run(100.0);
        assert!(
            (start - 0.5).abs() > 0.2,
            "the test needs a start away from the optimum: {start}"
        );
        assert!(
            (free - 0.5).abs() < 0.1,
            "unconstrained mean {free} should approach 0.5"
        );
        assert_eq!(free_lambda, 0.0, "a limit never reached leaves λ at 0");
        let (_, constrained, lambda) = run(2.0);
        assert!(lambda > 0.0, "costs above the limit raise λ");
        assert!(
            constrained < free - 0.1,
            "constrained mean {constrained} vs unconstrained {free}"
        );
    }

    #[test]
    fn a_restored_learner_updates_exactly_like_the_original_and_exports_what_it_acts() {
        for normalized in [false, true] {
            let mut s = settings();
            s.observation_normalization = normalized;
            let mut noise = Noise::seeded(9);
            let mut original = Learner::new(&s, 1, 1, 1.0, &mut noise).unwrap();
            let (rollout, costs) = bandit_from(&original, &mut noise, 100, f64::from, true);
            original.update(&rollout, &costs, 0.2, &mut noise).unwrap();
            let stats = original.state().observation_stats;
            assert_eq!(stats.is_some(), normalized);
            if let Some(stats) = stats {
                assert_eq!(stats.count, 100.0, "the update took in the collect's observations");
                assert!((stats.var[0] - 8.0 / 3.0).abs() < 0.1, "variance {:?}", stats.var);
            }
            let tensors: HashMap<String, Tensor> = original.tensors().into_iter().collect();
            let mut restored = Learner::restore(&s, 1.0, &tensors, &original.state()).unwrap();
            let (rollout, costs) = bandit_from(&original, &mut noise, 100, f64::from, true);
            let (mut n1, mut n2) = (noise, noise);
            let a = original.update(&rollout, &costs, 0.2, &mut n1).unwrap();
            let b = restored.update(&rollout, &costs, 0.2, &mut n2).unwrap();
            assert_eq!(a, b);
            assert_eq!(mean_action(&original), mean_action(&restored));
            assert_eq!(original.state(), restored.state());
            // The exported expert declares the statistics, so it acts on raw observations as the learner did.
            let dir = tempfile::tempdir().unwrap();
            original.write_policy(dir.path(), "OfflineBallRun-v0").unwrap();
            let (config, weights) = dsrl_policy::checkpoint::read(dir.path()).unwrap();
            assert_eq!(config.observation_normalization.is_some(), normalized);
            let policy = dsrl_policy::Policy::load(&config, &weights).unwrap();
            assert_eq!(
                policy.act(&matrix(&[0.5], 1, 1).unwrap()).unwrap(),
                vec![mean_action(&original)]
            );
            // A save and a recipe that disagree about normalization are refused, not mixed.
            let mut other = s.clone();
            other.observation_normalization = !normalized;
            let refused = Learner::restore(&other, 1.0, &tensors, &original.state())
                .err()
                .unwrap();
            assert!(refused.to_string().contains("observation_normalization"), "{refused}");
        }
    }
}
