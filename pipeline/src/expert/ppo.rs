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
    /// Mean of `log π_old − log π_new` over the minibatches of the last pass the actor took part in, each measured
    /// before its step.
    pub approx_kl: f64,
    pub std: f64,
    /// The actor's optimizer steps in this update: `repeat_per_collect` x minibatches, fewer where `target_kl`
    /// stopped it.
    #[serde(default)]
    pub actor_steps: u32,
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
        let mut learner = Self::warm_start(settings, max_action, tensors, state.observation_stats.clone())?;
        learner.actor_opt.restore("adam.actor", tensors, state.actor_steps)?;
        learner.critic_opt.restore("adam.critic", tensors, state.critic_steps)?;
        learner.lagrangian = state.lagrangian.clone();
        Ok(learner)
    }

    /// A learner that starts from another training's networks (actor, critics) and observation statistics, with
    /// fresh optimizers and a fresh multiplier (the recipe's `warm_start`; `restore` then adds the saved moments
    /// and multiplier). Optimizer moments in `tensors`, if any, are not read.
    pub fn warm_start(
        settings: &ExpertSettings,
        max_action: f64,
        tensors: &HashMap<String, Tensor>,
        observation_stats: Option<ObservationStats>,
    ) -> anyhow::Result<Learner> {
        anyhow::ensure!(
            settings.observation_normalization == observation_stats.is_some(),
            "the saved expert was trained {} observation normalization but the recipe now says \
             observation_normalization = {}: resume with the recipe it started with, or start a new state folder",
            if observation_stats.is_some() { "with" } else { "without" },
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
        let sizes = actor.mean_net.sizes();
        let hidden = &sizes[1..sizes.len().saturating_sub(1).max(1)];
        anyhow::ensure!(
            hidden == settings.hidden_sizes,
            "the saved networks have hidden sizes {hidden:?}, the recipe {:?}",
            settings.hidden_sizes
        );
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
            observation_stats,
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
        // With `target_kl`, the actor stops for the rest of the update at the first minibatch whose KL (measured
        // before its step) passes 1.5x the target; the critics go on with all their passes.
        let kl_stop = s.target_kl.map(|kl| 1.5 * kl);
        let mut actor_stopped = false;
        for pass in 0..s.repeat_per_collect {
            let order = noise.permutation(n);
            let (mut kl_sum, mut kl_batches, mut actor_sum, mut actor_batches) = (0.0, 0, 0.0, 0);
            let (mut critic_sum, mut batches) = (0.0, 0);
            for chunk in order.chunks(s.minibatch_size) {
                let idx = Tensor::from_slice(chunk, chunk.len(), dev)?;
                let obs_b = obs.index_select(&idx, 0)?;
                if !actor_stopped {
                    let log_probs = self.actor.log_prob(&obs_b, &actions.index_select(&idx, 0)?)?;
                    let old_b = old_log_probs.index_select(&idx, 0)?;
                    // Without a target the KL is only reported, from the last pass as before, so it is only
                    // computed there.
                    let kl = if kl_stop.is_some() || pass + 1 == s.repeat_per_collect {
                        Some(f64::from(old_b.sub(&log_probs)?.mean_all()?.to_scalar::<f32>()?))
                    } else {
                        None
                    };
                    if let Some(kl) = kl {
                        kl_sum += kl;
                        kl_batches += 1;
                    }
                    if kl_stop.zip(kl).is_some_and(|(stop, kl)| kl > stop) {
                        actor_stopped = true;
                    } else {
                        let adv_b = mixed.index_select(&idx, 0)?;
                        let ratio = log_probs.sub(&old_b)?.exp()?;
                        let clipped = ratio.clamp(1.0 - s.clip_ratio, 1.0 + s.clip_ratio)?;
                        let surrogate = ratio.mul(&adv_b)?.minimum(&clipped.mul(&adv_b)?)?;
                        let mut actor_loss = surrogate.mean_all()?.neg()?;
                        if let Some(coef) = s.entropy_coef {
                            // H(N(μ, σ)) = Σ log σ + const per state: the bonus only reaches log σ.
                            let entropy = self.actor.log_std.as_tensor().sum_all()?;
                            actor_loss = actor_loss.sub(&entropy.affine(coef, 0.0)?)?;
                        }
                        self.actor_opt.step(&actor_loss.backward()?)?;
                        actor_sum += f64::from(actor_loss.to_scalar::<f32>()?);
                        actor_batches += 1;
                        stats.actor_steps += 1;
                    }
                }

                let value_loss = |critic: &Mlp, target: &Tensor| -> anyhow::Result<Tensor> {
                    let v = critic.forward(&obs_b)?.flatten_all()?;
                    Ok(v.sub(&target.index_select(&idx, 0)?)?.sqr()?.mean_all()?)
                };
                let critic_loss =
                    value_loss(&self.reward_critic, &target_r)?.add(&value_loss(&self.cost_critic, &target_c)?)?;
                self.critic_opt.step(&critic_loss.backward()?)?;
                critic_sum += f64::from(critic_loss.to_scalar::<f32>()?);
                batches += 1;
            }
            if actor_batches > 0 {
                stats.actor_loss = actor_sum / f64::from(actor_batches);
            }
            if kl_batches > 0 {
                stats.approx_kl = kl_sum / f64::from(kl_batches);
            }
            stats.critic_loss = critic_sum / f64::from(batches);
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

    /// Mean `log π_old − log π_new` over a collect: how far an update moved the policy from the one that played it.
    fn kl_from_collect(learner: &Learner, rollout: &Rollout) -> f64 {
        let n = rollout.len();
        let new = learner
            .actor
            .log_prob(
                &matrix(&learner.inputs(&rollout.observations), n, 1).unwrap(),
                &matrix(&rollout.actions, n, 1).unwrap(),
            )
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        rollout
            .log_probs
            .iter()
            .zip(&new)
            .map(|(o, n)| f64::from(o - n))
            .sum::<f64>()
            / n as f64
    }

    #[test]
    fn target_kl_stops_the_actors_steps_and_bounds_how_far_an_update_moves_the_policy() {
        let mut s = settings();
        (s.repeat_per_collect, s.lr) = (10, 1e-2);
        let one_update = |s: &ExpertSettings| {
            let mut noise = Noise::seeded(3);
            let mut learner = Learner::new(s, 1, 1, 1.0, &mut noise).unwrap();
            let (rollout, costs) = bandit(&learner, &mut noise, 512, |_| 0.0);
            let stats = learner.update(&rollout, &costs, 100.0, &mut noise).unwrap();
            (stats, kl_from_collect(&learner, &rollout))
        };
        let (free, free_kl) = one_update(&s);
        assert_eq!(free.actor_steps, 10 * 8, "10 passes of 8 minibatches of 64");
        s.target_kl = Some(0.01);
        let (stopped, stopped_kl) = one_update(&s);
        assert!(
            stopped.actor_steps > 0 && stopped.actor_steps < free.actor_steps,
            "{} of {} steps",
            stopped.actor_steps,
            free.actor_steps
        );
        assert!(
            free_kl > 0.1 && stopped_kl < 0.03,
            "KL from the collect's policy: {free_kl} without a target, {stopped_kl} with 0.01"
        );
    }

    #[test]
    fn the_entropy_bonus_holds_sigma_up() {
        let final_std = |entropy_coef| {
            let mut s = settings();
            s.entropy_coef = entropy_coef;
            let mut noise = Noise::seeded(5);
            let mut learner = Learner::new(&s, 1, 1, 1.0, &mut noise).unwrap();
            let mut std = 0.0;
            for _ in 0..40 {
                let (rollout, costs) = bandit(&learner, &mut noise, 256, |_| 0.0);
                std = learner.update(&rollout, &costs, 100.0, &mut noise).unwrap().std;
            }
            std
        };
        // The bandit's reward only falls with σ, so it takes a large weight to hold σ up against it (the advantages
        // are normalized, so the weight is relative to a unit-scale surrogate).
        let (without, with) = (final_std(None), final_std(Some(1.0)));
        assert!(without < 0.2, "the bandit narrows σ from its initial 0.61: {without}");
        assert!(with > 0.4, "σ {with} with the bonus, {without} without");
    }

    #[test]
    fn a_warm_started_learner_acts_like_its_source_with_fresh_optimizers_and_multiplier() {
        let mut s = settings();
        s.observation_normalization = true;
        let mut noise = Noise::seeded(11);
        let mut source = Learner::new(&s, 1, 1, 1.0, &mut noise).unwrap();
        for _ in 0..3 {
            let (rollout, costs) = bandit_from(&source, &mut noise, 100, |a| 20.0 * f64::from(a.max(0.0)), true);
            source.update(&rollout, &costs, 1.0, &mut noise).unwrap();
        }
        assert!(source.lagrangian.lagrangian > 0.0 && source.state().actor_steps > 0);
        // The networks only, as `read_warm_start` takes them from a save.
        let networks: HashMap<String, Tensor> = source
            .tensors()
            .into_iter()
            .filter(|(name, _)| !name.starts_with("adam."))
            .collect();
        let stats = source.state().observation_stats;
        let warm = Learner::warm_start(&s, 1.0, &networks, stats.clone()).unwrap();
        assert_eq!(mean_action(&warm), mean_action(&source));
        assert_eq!(warm.state().observation_stats, stats);
        assert_eq!((warm.state().actor_steps, warm.state().critic_steps), (0, 0));
        assert_eq!(
            warm.lagrangian,
            PidLagrangian::new(s.lagrangian.kp, s.lagrangian.ki, s.lagrangian.kd)
        );
        // Networks of other shapes, or a recipe that disagrees about normalization, are refused.
        let mut wider = s.clone();
        wider.hidden_sizes = vec![32, 32];
        let err = Learner::warm_start(&wider, 1.0, &networks, stats.clone())
            .err()
            .unwrap();
        assert!(err.to_string().contains("hidden sizes"), "{err}");
        let err = Learner::warm_start(&s, 1.0, &networks, None).err().unwrap();
        assert!(err.to_string().contains("observation_normalization"), "{err}");
    }
}
