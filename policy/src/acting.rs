//! A loaded checkpoint, ready to act: the network its `policy.json` declares, built from its weights with every
//! tensor checked, and [`Rollout`]s that play it in several environments at once.
//!
//! A rollout keeps what a policy carries through an episode: the CDT's context (states, actions, reward- and
//! cost-to-go so far), the BCQ actor's latent generator, seeded with the episode's seed, and CAPS's cost received
//! and steps taken. The evaluator starts
//! an episode in an environment slot, asks for actions for any subset of slots, and reports each step's reward and
//! cost; the policy's actions are deterministic given the episode seeds, whatever the batching.

use std::collections::HashMap;

use candle_core::{Device, Tensor};

use crate::bcq::{self, BcqActor, BcqShape};
use crate::caps::{CapsNetworks, CapsShape, per_step_limit};
use crate::cdt::{self, Cdt, CdtContext, CdtShape};
use crate::checkpoint::{Architecture, CONFIG_FILE, Conditioning, DiffusionSampler, PolicyConfig};
use crate::diffusion::{DiffusionPolicy, DiffusionShape, NoiseNet, Sampler, Schedule};
use crate::gaussian::GaussianActor;
use crate::latent::{LatentPolicy, LatentShape, LatentSource};
use crate::layers::Weights;
use crate::mlp::{Activation, Mlp, layer_sizes};
use crate::noise::Noise;
use crate::{PolicyError, Result};

/// The network of a loaded policy.
pub enum Network {
    Gaussian(GaussianActor),
    /// `max_action · tanh(net(obs))`.
    Mlp {
        net: Mlp,
        max_action: f64,
    },
    /// `max_action · tanh(mu(activation(trunk(obs))))`.
    Squashed {
        trunk: Mlp,
        mu: Mlp,
        activation: Activation,
        max_action: f64,
    },
    Bcq(BcqActor),
    Cdt {
        model: Cdt,
        max_action: f64,
        reward_scale: f64,
        cost_scale: f64,
    },
    Caps {
        nets: CapsNetworks,
        max_action: f64,
        gamma: f64,
        episode_len: usize,
        cost_scale: f64,
    },
    Diffusion(DiffusionPolicy),
    Latent(LatentPolicy),
}

fn format_error(message: impl Into<String>) -> PolicyError {
    PolicyError::Format(message.into())
}

impl Network {
    /// Builds the declared architecture, its constants checked first; `input_dim` is what the network reads (the
    /// observation, and the cost threshold after it for `target_cost` conditioning).
    fn load(config: &PolicyConfig, input_dim: usize, tensors: &HashMap<String, Tensor>) -> Result<Network> {
        config.architecture.check_constants()?;
        let act_dim = config.act_dim;
        let mut w = Weights::new(tensors);
        let (network, training_only): (Network, &[&str]) = match &config.architecture {
            Architecture::GaussianMlp {
                hidden_sizes,
                activation,
                max_action,
            } => {
                let mean_net = w.mlp("actor.mu", &layer_sizes(input_dim, hidden_sizes, act_dim), *activation)?;
                let log_std = w.var("actor.log_std", &[act_dim])?;
                let actor = GaussianActor {
                    mean_net,
                    log_std,
                    max_action: *max_action,
                };
                (Network::Gaussian(actor), &[])
            }
            Architecture::MlpActor {
                hidden_sizes,
                activation,
                max_action,
            } => {
                let net = w.mlp("actor.net", &layer_sizes(input_dim, hidden_sizes, act_dim), *activation)?;
                (
                    Network::Mlp {
                        net,
                        max_action: *max_action,
                    },
                    &[],
                )
            }
            Architecture::SquashedGaussianMlp {
                hidden_sizes,
                activation,
                max_action,
            } => {
                let Some(&last) = hidden_sizes.last() else {
                    return Err(format_error("squashed_gaussian_mlp needs at least one hidden layer"));
                };
                let mut trunk_sizes = vec![input_dim];
                trunk_sizes.extend(hidden_sizes);
                let trunk = w.mlp("actor.trunk", &trunk_sizes, *activation)?;
                let mu = w.mlp("actor.mu", &[last, act_dim], *activation)?;
                let network = Network::Squashed {
                    trunk,
                    mu,
                    activation: *activation,
                    max_action: *max_action,
                };
                // The log-std head only matters when sampling.
                (network, &["actor.log_std."])
            }
            Architecture::BcqActor {
                hidden_sizes,
                activation,
                decoder_hidden_sizes,
                latent_dim,
                phi,
                max_action,
            } => {
                let shape = BcqShape {
                    input_dim,
                    act_dim,
                    latent_dim: *latent_dim,
                    hidden_sizes,
                    decoder_hidden_sizes,
                };
                let actor = BcqActor::from_weights(&shape, *activation, *phi, *max_action, &mut w)?;
                (Network::Bcq(actor), &bcq::TRAINING_ONLY)
            }
            Architecture::Cdt {
                embedding_dim,
                num_layers,
                num_heads,
                seq_len,
                episode_len,
                max_action,
                reward_scale,
                cost_scale,
                cost_transform,
            } => {
                let shape = CdtShape {
                    obs_dim: input_dim,
                    act_dim,
                    embedding_dim: *embedding_dim,
                    num_layers: *num_layers,
                    num_heads: *num_heads,
                    seq_len: *seq_len,
                    episode_len: *episode_len,
                };
                let model = Cdt::from_weights(shape, *cost_transform, &mut w)?;
                let network = Network::Cdt {
                    model,
                    max_action: *max_action,
                    reward_scale: *reward_scale,
                    cost_scale: *cost_scale,
                };
                (network, &cdt::TRAINING_ONLY)
            }
            Architecture::Caps {
                hidden_sizes,
                num_heads,
                max_action,
                gamma,
                episode_len,
                cost_scale,
            } => {
                let shape = CapsShape {
                    obs_dim: input_dim,
                    act_dim,
                    hidden_sizes: hidden_sizes.clone(),
                    num_heads: *num_heads,
                };
                let network = Network::Caps {
                    nets: CapsNetworks::from_weights(shape, &mut w)?,
                    max_action: *max_action,
                    gamma: *gamma,
                    episode_len: *episode_len,
                    cost_scale: *cost_scale,
                };
                // The value networks only train the critics.
                (network, &["reward_v.", "cost_v."])
            }
            Architecture::Diffusion {
                time_dim,
                cond_sizes,
                hidden_dim,
                num_blocks,
                layer_norm,
                critic_hidden_sizes,
                critic_members,
                max_action,
                sampler:
                    DiffusionSampler::Ddpm {
                        steps,
                        beta_min,
                        beta_max,
                        clip,
                        temperature,
                        candidates,
                        choice,
                    },
            } => {
                let shape = DiffusionShape {
                    obs_dim: input_dim,
                    act_dim,
                    time_dim: *time_dim,
                    cond_sizes: cond_sizes.clone(),
                    hidden_dim: *hidden_dim,
                    num_blocks: *num_blocks,
                    layer_norm: *layer_norm,
                };
                let net = NoiseNet::from_weights(shape, "actor", &mut w)?;
                let critic = DiffusionPolicy::critic_from_weights(
                    *choice,
                    *critic_members,
                    input_dim + act_dim,
                    critic_hidden_sizes,
                    &mut w,
                )?;
                let policy = DiffusionPolicy {
                    net,
                    sampler: Sampler {
                        schedule: Schedule::vp(*steps, *beta_min, *beta_max),
                        candidates: *candidates,
                        clip: *clip,
                        temperature: *temperature,
                    },
                    critic,
                    choice: *choice,
                    max_action: *max_action,
                };
                // The other critics and the value networks only train.
                (
                    Network::Diffusion(policy),
                    &["reward_q.", "cost_q.", "reward_v.", "cost_v."],
                )
            }
            Architecture::LatentPolicy {
                hidden_sizes,
                decoder_hidden_sizes,
                latent_dim,
                max_latent,
                latent,
                max_action,
            } => {
                let shape = LatentShape {
                    obs_dim: input_dim,
                    act_dim,
                    latent_dim: *latent_dim,
                    hidden_sizes: hidden_sizes.clone(),
                    decoder_hidden_sizes: decoder_hidden_sizes.clone(),
                };
                let policy = LatentPolicy::from_weights(shape, *latent, *max_latent, *max_action, &mut w)?;
                let training_only: &[&str] = match latent {
                    LatentSource::SafetyEncoder => &crate::latent::TRAINING_ONLY,
                    LatentSource::Prior => &crate::latent::TRAINING_ONLY_PRIOR,
                };
                (Network::Latent(policy), training_only)
            }
        };
        w.finish(training_only)?;
        Ok(network)
    }

    /// Deterministic actions of a network that keeps nothing between steps, `[batch, act_dim]` row-major.
    fn act_memoryless(&self, obs: &Tensor) -> Result<Option<Vec<f32>>> {
        let out = match self {
            Network::Gaussian(actor) => actor.mean(obs)?,
            Network::Mlp { net, max_action } => net.forward(obs)?.tanh()?.affine(*max_action, 0.0)?,
            Network::Squashed {
                trunk,
                mu,
                activation,
                max_action,
            } => {
                // The trunk's activation also follows its last layer.
                let h = activation.apply(&trunk.forward(obs)?)?;
                mu.forward(&h)?.tanh()?.affine(*max_action, 0.0)?
            }
            Network::Bcq(_)
            | Network::Cdt { .. }
            | Network::Caps { .. }
            | Network::Diffusion(_)
            | Network::Latent(_) => return Ok(None),
        };
        Ok(Some(out.flatten_all()?.to_vec1::<f32>()?))
    }
}

/// A loaded policy: its network, the observation normalization and the conditioning it declares.
pub struct Policy {
    pub network: Network,
    /// `(mean, std)` per observation feature.
    normalization: Option<(Vec<f32>, Vec<f32>)>,
    conditioning: Conditioning,
    obs_dim: usize,
    act_dim: usize,
}

impl Policy {
    /// Builds the architecture the config declares from the weights, checking names and shapes against it and
    /// the conditioning against the architecture.
    pub fn load(config: &PolicyConfig, tensors: &HashMap<String, Tensor>) -> Result<Policy> {
        let normalization = match &config.observation_normalization {
            None => None,
            Some(n) => {
                if n.mean.len() != config.obs_dim || n.std.len() != config.obs_dim {
                    return Err(format_error(format!(
                        "observation_normalization needs {} means and stds, got {} and {}",
                        config.obs_dim,
                        n.mean.len(),
                        n.std.len()
                    )));
                }
                if n.std.iter().any(|s| !(s.is_finite() && *s > 0.0)) || n.mean.iter().any(|m| !m.is_finite()) {
                    return Err(format_error(
                        "observation_normalization: every std must be positive and finite, every mean finite",
                    ));
                }
                Some((n.mean.clone(), n.std.clone()))
            }
        };
        let is_cdt = matches!(config.architecture, Architecture::Cdt { .. });
        let is_caps = matches!(config.architecture, Architecture::Caps { .. });
        if is_caps != (config.conditioning == Conditioning::CostBudget) {
            return Err(format_error(format!(
                "{CONFIG_FILE}: conditioning cost_budget goes with the caps architecture, and caps with it; got {} \
                 with {}",
                config.conditioning.kind(),
                config.architecture.name()
            )));
        }
        match &config.conditioning {
            Conditioning::ReturnsToGo { targets } => {
                if !is_cdt {
                    return Err(format_error(format!(
                        "{CONFIG_FILE}: conditioning returns_to_go is for the cdt architecture, not {}",
                        config.architecture.name()
                    )));
                }
                if targets.is_empty() {
                    return Err(format_error("returns_to_go: targets is empty"));
                }
                for (i, t) in targets.iter().enumerate() {
                    if ![t.cost_threshold, t.reward_return, t.cost_return]
                        .iter()
                        .all(|v| v.is_finite())
                    {
                        return Err(format_error(format!("returns_to_go: target {i} is not finite")));
                    }
                    if targets[..i].iter().any(|u| u.cost_threshold == t.cost_threshold) {
                        return Err(format_error(format!(
                            "returns_to_go: two targets for cost threshold {}",
                            t.cost_threshold
                        )));
                    }
                }
            }
            other if is_cdt => {
                return Err(format_error(format!(
                    "{CONFIG_FILE}: a cdt is conditioned on returns-to-go: conditioning must be {{\"kind\": \
                     \"returns_to_go\", \"targets\": [{{\"cost_threshold\", \"reward_return\", \"cost_return\"}}, ...]}}, \
                     not {}",
                    serde_json::to_string(other).unwrap_or_default()
                )));
            }
            Conditioning::PerThreshold { cost_threshold } if !cost_threshold.is_finite() => {
                return Err(format_error("per_threshold: cost_threshold is not finite"));
            }
            _ => {}
        }
        let input_dim = config.obs_dim + usize::from(config.conditioning == Conditioning::TargetCost);
        Ok(Policy {
            network: Network::load(config, input_dim, tensors)?,
            normalization,
            conditioning: config.conditioning.clone(),
            obs_dim: config.obs_dim,
            act_dim: config.act_dim,
        })
    }

    /// `(obs − mean) / std` when the policy declares a normalization, then the cost threshold appended to each
    /// row for `target_cost` conditioning; row-major, `rows` rows.
    fn network_input(&self, obs: &[f32], rows: usize, cost_threshold: f32) -> Vec<f32> {
        let d = self.obs_dim;
        let extra = usize::from(self.conditioning == Conditioning::TargetCost);
        let mut out = Vec::with_capacity(rows * (d + extra));
        for row in obs.chunks(d).take(rows) {
            match &self.normalization {
                None => out.extend_from_slice(row),
                Some((mean, std)) => out.extend(row.iter().zip(mean.iter().zip(std)).map(|(x, (m, s))| (x - m) / s)),
            }
            if extra == 1 {
                out.push(cost_threshold);
            }
        }
        out
    }

    /// Deterministic actions (the mean for stochastic actors), row-major `[batch, act_dim]`, for a policy that
    /// needs neither a threshold nor an episode's history; others act through [`Policy::rollout`].
    pub fn act(&self, obs: &Tensor) -> Result<Vec<f32>> {
        if self.conditioning.is_conditioned() {
            return Err(format_error(
                "a conditioned policy acts through a rollout at a cost threshold",
            ));
        }
        let (rows, _) = obs.dims2()?;
        let input = self.network_input(&obs.flatten_all()?.to_vec1::<f32>()?, rows, 0.0);
        let input = Tensor::from_vec(input, (rows, self.obs_dim), &Device::Cpu)?;
        self.network
            .act_memoryless(&input)?
            .ok_or_else(|| format_error("this architecture acts through a rollout (it keeps state per episode)"))
    }

    /// A rollout scoring the policy at `cost_threshold` in `envs` environment slots.
    pub fn rollout(&self, cost_threshold: f64, envs: usize) -> Result<Rollout<'_>> {
        let start = self.episode_start(cost_threshold)?;
        Ok(Rollout::new(Held::Borrowed(self), cost_threshold, start, envs))
    }

    /// [`Policy::rollout`] for a holder that keeps the rollout between calls without the policy (a simulator
    /// session playing it, `dsrl-sim-worker`): the rollout shares the policy.
    pub fn shared_rollout(self: std::sync::Arc<Self>, cost_threshold: f64, envs: usize) -> Result<Rollout<'static>> {
        let start = self.episode_start(cost_threshold)?;
        Ok(Rollout::new(Held::Shared(self), cost_threshold, start, envs))
    }

    /// What every episode's CDT context starts from: the scaled target `(R̂_0, Ĉ_0)` declared for `cost_threshold`
    /// (zeros for other policies).
    fn episode_start(&self, cost_threshold: f64) -> Result<(f32, f32)> {
        Ok(match (&self.conditioning, &self.network) {
            (
                Conditioning::ReturnsToGo { targets },
                Network::Cdt {
                    reward_scale,
                    cost_scale,
                    ..
                },
            ) => {
                let target = targets
                    .iter()
                    .find(|t| t.cost_threshold == cost_threshold)
                    .ok_or_else(|| {
                        format_error(format!(
                            "returns_to_go declares no target for cost threshold {cost_threshold}"
                        ))
                    })?;
                (
                    (target.reward_return * reward_scale) as f32,
                    (target.cost_return * cost_scale) as f32,
                )
            }
            _ => (0.0, 0.0),
        })
    }
}

/// What the policy keeps for the episode an environment slot is playing.
struct EpisodeState {
    /// The policy's own random draws: the BCQ actor's and a latent policy's latents, a diffusion sampler's noise.
    latents: Noise,
    /// The CDT's inputs so far.
    context: CdtContext,
    /// The cost received so far (scaled as the policy's critics see it) and the steps taken: what a budget-adaptive
    /// policy (CAPS) has left.
    spent: f64,
    steps: usize,
}

impl EpisodeState {
    fn new(latents: Noise, start: (f32, f32)) -> EpisodeState {
        EpisodeState {
            latents,
            context: CdtContext::new(start.0, start.1),
            spent: 0.0,
            steps: 0,
        }
    }
}

/// The policy a [`Rollout`] plays: borrowed from its caller, or shared with it.
#[derive(Clone)]
enum Held<'p> {
    Borrowed(&'p Policy),
    Shared(std::sync::Arc<Policy>),
}

impl std::ops::Deref for Held<'_> {
    type Target = Policy;

    fn deref(&self) -> &Policy {
        match self {
            Held::Borrowed(policy) => policy,
            Held::Shared(policy) => policy,
        }
    }
}

/// A policy playing episodes in a fixed number of environment slots at one cost threshold.
pub struct Rollout<'p> {
    policy: Held<'p>,
    cost_threshold: f32,
    /// The CDT's scaled `(R̂_0, Ĉ_0)`.
    start: (f32, f32),
    episodes: Vec<EpisodeState>,
}

impl<'p> Rollout<'p> {
    fn new(policy: Held<'p>, cost_threshold: f64, start: (f32, f32), envs: usize) -> Rollout<'p> {
        Rollout {
            policy,
            cost_threshold: cost_threshold as f32,
            start,
            episodes: (0..envs).map(|_| EpisodeState::new(Noise::seeded(0), start)).collect(),
        }
    }

    /// Starts a new episode in slot `env`; `seed` (the episode's seed) seeds the policy's own random draws.
    pub fn start_episode(&mut self, env: usize, seed: u64) -> Result<()> {
        let slot = self
            .episodes
            .get_mut(env)
            .ok_or_else(|| format_error(format!("no environment slot {env}")))?;
        *slot = EpisodeState::new(Noise::seeded(seed), self.start);
        Ok(())
    }

    /// The slots `envs` (strictly increasing), mutably, in order.
    fn slots(&mut self, envs: &[u32]) -> Result<Vec<&mut EpisodeState>> {
        if envs.windows(2).any(|w| w[0] >= w[1]) || envs.last().is_some_and(|&e| e as usize >= self.episodes.len()) {
            return Err(format_error(format!(
                "environment slots {envs:?} must be increasing and below {}",
                self.episodes.len()
            )));
        }
        let mut wanted = envs.iter().peekable();
        let mut out = Vec::with_capacity(envs.len());
        for (i, slot) in self.episodes.iter_mut().enumerate() {
            if wanted.peek().is_some_and(|&&e| e as usize == i) {
                wanted.next();
                out.push(slot);
            }
        }
        Ok(out)
    }

    /// Actions for the environments `envs` (strictly increasing slots) given their observations (row-major),
    /// row-major `[envs, act_dim]`.
    pub fn act(&mut self, envs: &[u32], observations: &[f32]) -> Result<Vec<f32>> {
        // A handle of its own (a reference, or one more count of a shared policy): the slots below borrow `self`.
        let held = self.policy.clone();
        let policy: &Policy = &held;
        let n = envs.len();
        if observations.len() != n * policy.obs_dim {
            return Err(format_error(format!(
                "{} observation values for {n} environments of observation dim {}",
                observations.len(),
                policy.obs_dim
            )));
        }
        let input = policy.network_input(observations, n, self.cost_threshold);
        let input_dim = input.len() / n.max(1);
        let actions = match &policy.network {
            Network::Bcq(actor) => {
                let mut slots = self.slots(envs)?;
                let mut generators: Vec<&mut Noise> = slots.iter_mut().map(|s| &mut s.latents).collect();
                let z = actor.latents(&mut generators)?;
                let obs = Tensor::from_vec(input, (n, input_dim), &Device::Cpu)?;
                actor.act(&obs, &z)?.flatten_all()?.to_vec1::<f32>()?
            }
            Network::Diffusion(diffusion) => {
                let mut slots = self.slots(envs)?;
                let mut generators: Vec<&mut Noise> = slots.iter_mut().map(|s| &mut s.latents).collect();
                let obs = Tensor::from_vec(input, (n, input_dim), &Device::Cpu)?;
                diffusion.act(&obs, &mut generators)?
            }
            Network::Latent(latent) => {
                let mut slots = self.slots(envs)?;
                let mut generators: Vec<&mut Noise> = slots.iter_mut().map(|s| &mut s.latents).collect();
                let obs = Tensor::from_vec(input, (n, input_dim), &Device::Cpu)?;
                latent.act(&obs, &mut generators)?
            }
            Network::Cdt { model, max_action, .. } => {
                let mut slots = self.slots(envs)?;
                let mut contexts: Vec<&mut CdtContext> = slots.iter_mut().map(|s| &mut s.context).collect();
                model.act(&mut contexts, &input, *max_action)?
            }
            Network::Caps {
                nets,
                max_action,
                gamma,
                episode_len,
                cost_scale,
            } => {
                let budget = f64::from(self.cost_threshold) * cost_scale;
                let limits: Vec<f64> = self
                    .slots(envs)?
                    .iter()
                    .map(|s| per_step_limit(budget - s.spent, s.steps, *episode_len, *gamma))
                    .collect();
                let obs = Tensor::from_vec(input, (n, input_dim), &Device::Cpu)?;
                nets.switch(&obs, &limits, *max_action)?
            }
            network => {
                let obs = Tensor::from_vec(input, (n, input_dim), &Device::Cpu)?;
                network.act_memoryless(&obs)?.unwrap_or_default()
            }
        };
        if actions.len() != n * policy.act_dim {
            return Err(format_error(format!(
                "the policy produced {} action values for {n} environments of action dim {}",
                actions.len(),
                policy.act_dim
            )));
        }
        // A non-finite value anywhere in the forward pass reaches the actions (NaN propagates through every layer,
        // ReLU included, as in PyTorch): the evaluation fails with the reason rather than play a broken network.
        if let Some(i) = actions.iter().position(|a| !a.is_finite()) {
            return Err(format_error(format!(
                "the policy produced a non-finite action ({}) for environment {}: a NaN or infinity in its forward \
                 pass",
                actions[i],
                envs[i / policy.act_dim.max(1)]
            )));
        }
        Ok(actions)
    }

    /// Records the reward and cost each of `envs` received for its last action: what a return-conditioned policy
    /// subtracts from its reward- and cost-to-go, and what a budget-adaptive one (CAPS) takes off its budget.
    pub fn observe(&mut self, envs: &[u32], rewards: &[f64], costs: &[f64]) -> Result<()> {
        match self.policy.network {
            Network::Cdt {
                reward_scale,
                cost_scale,
                ..
            } => {
                for ((slot, r), c) in self.slots(envs)?.into_iter().zip(rewards).zip(costs) {
                    slot.context.record((r * reward_scale) as f32, (c * cost_scale) as f32);
                }
            }
            Network::Caps { cost_scale, .. } => {
                for (slot, c) in self.slots(envs)?.into_iter().zip(costs) {
                    slot.spent += c * cost_scale;
                    slot.steps += 1;
                }
            }
            _ => {}
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::checkpoint::{FORMAT, ObservationNormalization, ReturnTarget};
    use crate::gaussian::matrix;

    fn with(architecture: Architecture, normalization: Option<ObservationNormalization>) -> PolicyConfig {
        PolicyConfig {
            format: FORMAT.into(),
            task: "OfflineCarRun-v0".into(),
            obs_dim: 3,
            act_dim: 2,
            architecture,
            observation_normalization: normalization,
            conditioning: Conditioning::Unconditioned,
            training: None,
        }
    }

    fn mlp_actor(hidden: usize) -> Architecture {
        Architecture::MlpActor {
            hidden_sizes: vec![hidden],
            activation: Activation::Relu,
            max_action: 2.0,
        }
    }

    #[test]
    fn every_architecture_acts_as_its_definition_and_applies_the_declared_normalization() {
        let mut noise = Noise::seeded(3);
        let obs = matrix(&[0.5, -1.0, 2.0, 0.1, 0.2, 0.3], 2, 3).unwrap();

        // mlp_actor: 2·tanh(net(obs)).
        let net = Mlp::orthogonal("actor.net", &[3, 8, 2], Activation::Relu, 1.0, 1.0, &mut noise).unwrap();
        let config = with(mlp_actor(8), None);
        let tensors: HashMap<String, Tensor> = crate::tensors_of(net.named_vars()).into_iter().collect();
        let policy = Policy::load(&config, &tensors).unwrap();
        let want = net.forward(&obs).unwrap().tanh().unwrap().affine(2.0, 0.0).unwrap();
        assert_eq!(
            policy.act(&obs).unwrap(),
            want.flatten_all().unwrap().to_vec1::<f32>().unwrap()
        );

        // The declared normalization is applied before the network.
        let normalization = ObservationNormalization {
            mean: vec![1.0, 0.0, -1.0],
            std: vec![2.0, 1.0, 0.5],
        };
        let normalized = Policy::load(&with(mlp_actor(8), Some(normalization)), &tensors).unwrap();
        let by_hand = matrix(&[-0.25, -1.0, 6.0, -0.45, 0.2, 2.6], 2, 3).unwrap();
        let got = normalized.act(&obs).unwrap();
        for (a, b) in got.iter().zip(policy.act(&by_hand).unwrap()) {
            assert!((a - b).abs() < 1e-6, "{got:?}");
        }
        let bad = ObservationNormalization {
            mean: vec![0.0; 3],
            std: vec![1.0, 0.0, 1.0],
        };
        let err = Policy::load(&with(mlp_actor(8), Some(bad)), &tensors).err().unwrap();
        assert!(err.to_string().contains("every std must be positive"), "{err}");

        // A tensor the architecture has no place for is refused, not ignored.
        let mut surplus = tensors.clone();
        surplus.insert(
            "actor.net.2.weight".into(),
            Tensor::zeros((2, 2), candle_core::DType::F32, &Device::Cpu).unwrap(),
        );
        surplus.insert(
            "actor.net.2.bias".into(),
            Tensor::zeros(2, candle_core::DType::F32, &Device::Cpu).unwrap(),
        );
        let err = Policy::load(&config, &surplus).err().unwrap().to_string();
        assert!(err.contains("actor.net has layer sizes [3, 8, 2, 2]"), "{err}");

        // squashed_gaussian_mlp: tanh(mu(relu(trunk(obs)))), the trunk's activation after its last layer too.
        let trunk = Mlp::orthogonal("actor.trunk", &[3, 8, 8], Activation::Relu, 1.0, 1.0, &mut noise).unwrap();
        let mu = Mlp::orthogonal("actor.mu", &[8, 2], Activation::Relu, 1.0, 1.0, &mut noise).unwrap();
        let log_std = Mlp::orthogonal("actor.log_std", &[8, 2], Activation::Relu, 1.0, 1.0, &mut noise).unwrap();
        let mut all = crate::tensors_of(trunk.named_vars());
        all.extend(crate::tensors_of(mu.named_vars()));
        all.extend(crate::tensors_of(log_std.named_vars()));
        let tensors: HashMap<String, Tensor> = all.into_iter().collect();
        let squashed = |hidden: Vec<usize>| {
            with(
                Architecture::SquashedGaussianMlp {
                    hidden_sizes: hidden,
                    activation: Activation::Relu,
                    max_action: 1.0,
                },
                None,
            )
        };
        let policy = Policy::load(&squashed(vec![8, 8]), &tensors).unwrap();
        let h = trunk.forward(&obs).unwrap().relu().unwrap();
        let want = mu.forward(&h).unwrap().tanh().unwrap();
        assert_eq!(
            policy.act(&obs).unwrap(),
            want.flatten_all().unwrap().to_vec1::<f32>().unwrap()
        );
        let err = Policy::load(&squashed(vec![8, 4]), &tensors).err().unwrap().to_string();
        assert!(err.contains("actor.trunk has layer sizes [3, 8, 8]"), "{err}");
    }

    #[test]
    fn target_cost_conditioning_appends_the_threshold_to_the_observation() {
        let net = Mlp::orthogonal(
            "actor.net",
            &[4, 8, 2],
            Activation::Relu,
            1.0,
            1.0,
            &mut Noise::seeded(5),
        )
        .unwrap();
        let tensors: HashMap<String, Tensor> = crate::tensors_of(net.named_vars()).into_iter().collect();
        let mut config = with(mlp_actor(8), None);
        // Unconditioned, the network would read 3 features; it has 4.
        let err = Policy::load(&config, &tensors).err().unwrap().to_string();
        assert!(
            err.contains("actor.net has layer sizes [4, 8, 2]") && err.contains("[3, 8, 2]"),
            "{err}"
        );
        config.conditioning = Conditioning::TargetCost;
        let policy = Policy::load(&config, &tensors).unwrap();
        assert!(policy.act(&matrix(&[0.0; 3], 1, 3).unwrap()).is_err());
        let obs = [0.5f32, -1.0, 2.0];
        let at = |k: f64| policy.rollout(k, 1).unwrap().act(&[0], &obs).unwrap();
        let by_hand = |k: f32| {
            let x = matrix(&[0.5, -1.0, 2.0, k], 1, 4).unwrap();
            net.forward(&x)
                .unwrap()
                .tanh()
                .unwrap()
                .affine(2.0, 0.0)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()
        };
        assert_eq!(at(10.0), by_hand(10.0));
        assert_eq!(at(40.0), by_hand(40.0));
        assert_ne!(at(10.0), at(40.0));
    }

    fn cdt_config(conditioning: Conditioning) -> PolicyConfig {
        PolicyConfig {
            conditioning,
            ..with(
                Architecture::Cdt {
                    embedding_dim: 16,
                    num_layers: 1,
                    num_heads: 2,
                    seq_len: 3,
                    episode_len: 10,
                    max_action: 1.0,
                    reward_scale: 0.1,
                    cost_scale: 1.0,
                    cost_transform: true,
                },
                None,
            )
        }
    }

    #[test]
    fn a_cdt_plays_from_its_declared_targets_and_keeps_each_episode_apart() {
        let shape = CdtShape {
            obs_dim: 3,
            act_dim: 2,
            embedding_dim: 16,
            num_layers: 1,
            num_heads: 2,
            seq_len: 3,
            episode_len: 10,
        };
        let model = Cdt::new(shape, true, &mut Noise::seeded(8)).unwrap();
        let tensors: HashMap<String, Tensor> = crate::tensors_of(model.named_vars()).into_iter().collect();
        let err = Policy::load(&cdt_config(Conditioning::Unconditioned), &tensors)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("conditioned on returns-to-go"), "{err}");
        let targets = vec![
            ReturnTarget {
                cost_threshold: 10.0,
                reward_return: 300.0,
                cost_return: 10.0,
            },
            ReturnTarget {
                cost_threshold: 20.0,
                reward_return: 350.0,
                cost_return: 20.0,
            },
        ];
        let policy = Policy::load(&cdt_config(Conditioning::ReturnsToGo { targets }), &tensors).unwrap();
        assert!(
            policy
                .rollout(40.0, 1)
                .err()
                .unwrap()
                .to_string()
                .contains("no target for cost threshold 40")
        );

        // Slot 0 plays two steps; slot 1 starts later: its first action equals a fresh episode's.
        let obs = [0.3f32, -0.2, 0.1, 0.3, -0.2, 0.1];
        let mut rollout = policy.rollout(10.0, 2).unwrap();
        rollout.start_episode(0, 1).unwrap();
        rollout.act(&[0], &obs[..3]).unwrap();
        rollout.observe(&[0], &[5.0], &[1.0]).unwrap();
        rollout.start_episode(1, 2).unwrap();
        let both = rollout.act(&[0, 1], &obs).unwrap();
        let mut fresh = policy.rollout(10.0, 1).unwrap();
        let first = fresh.act(&[0], &obs[..3]).unwrap();
        for (a, b) in both[2..].iter().zip(&first) {
            assert!((a - b).abs() < 1e-6);
        }
        assert_ne!(both[..2], first[..]);
        // The threshold selects the target: another threshold, another action.
        let other = policy.rollout(20.0, 1).unwrap().act(&[0], &obs[..3]).unwrap();
        assert_ne!(other, first);
        assert!(rollout.act(&[1, 0], &obs).is_err());
    }
}
