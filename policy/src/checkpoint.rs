//! The policy checkpoint format: a folder with `policy.safetensors` (float32 weights, named like PyTorch modules)
//! and `policy.json` (what the weights are: task, architecture and its hyperparameters, dimensions, optional
//! observation normalization, conditioning). Experts trained by `dsrl-admin collect` are written in this format so
//! they can be scored like any submission.
//!
//! Reading is buffered with limits (file size, tensor count), never memory-mapped, and every mismatch is a
//! [`PolicyError::Format`] that names the problem.

use std::collections::HashMap;
use std::io::Read;
use std::path::Path;

use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::mlp::Activation;
use crate::{PolicyError, Result};

pub const WEIGHTS_FILE: &str = "policy.safetensors";
pub const CONFIG_FILE: &str = "policy.json";
pub const FORMAT: &str = "dsrl-policy/1";
/// Largest weights file read (the paper's largest policies are well under 10 MB).
pub const MAX_WEIGHTS_BYTES: u64 = 64 << 20;
pub const MAX_CONFIG_BYTES: u64 = 64 << 10;
pub const MAX_TENSORS: usize = 256;
/// Largest safetensors JSON header read: 256 entries take a few tens of kilobytes.
pub const MAX_HEADER_BYTES: u64 = 256 << 10;
/// Longest tensor name.
pub const MAX_TENSOR_NAME: usize = 256;
/// Highest tensor rank any architecture uses (weights are 2-D; the CDT's position tables too).
pub const MAX_TENSOR_RANK: usize = 4;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PolicyConfig {
    /// Always [`FORMAT`].
    pub format: String,
    /// The offline task id (`OfflineCarRun-v0`).
    pub task: String,
    pub obs_dim: usize,
    pub act_dim: usize,
    pub architecture: Architecture,
    /// `obs ← (obs − mean) / std` before the network, when present.
    #[serde(default)]
    pub observation_normalization: Option<ObservationNormalization>,
    /// Which cost thresholds the policy is meant for.
    #[serde(default)]
    pub conditioning: Conditioning,
    /// Free-form record of how the policy was trained (dataset version, seed, steps); not interpreted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub training: Option<serde_json::Value>,
}

impl PolicyConfig {
    /// What the network reads per environment: the observation, and the cost threshold after it under `target_cost`
    /// conditioning.
    pub fn input_dim(&self) -> usize {
        self.obs_dim + usize::from(matches!(self.conditioning, Conditioning::TargetCost))
    }

    /// What one action costs by the declared sizes ([`Architecture::step_cost`] at this input and action size).
    pub fn step_cost(&self) -> StepCost {
        self.architecture.step_cost(self.input_dim(), self.act_dim)
    }

    /// [`Architecture::check_step_cost`] at this input and action size.
    pub fn check_step_cost(&self) -> Result<()> {
        self.architecture.check_step_cost(self.input_dim(), self.act_dim)
    }
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Conditioning {
    /// One policy for every threshold (BC-All, the experts).
    #[default]
    Unconditioned,
    /// Trained for one cost threshold (BC-Safe, the Lagrangian learners): scored at that threshold only.
    PerThreshold { cost_threshold: f64 },
    /// One policy for every threshold, told the threshold it is scored at: the network reads it as one more input
    /// after the observation (OSRL BC's multi-task mode appends the target cost the same way).
    TargetCost,
    /// A return-conditioned sequence model (`cdt`): for each threshold, the reward and cost return an episode starts
    /// out aiming for (OSRL's CDT `target_returns`); one policy for every threshold.
    ReturnsToGo { targets: Vec<ReturnTarget> },
    /// One policy for every threshold, given the threshold as the episode's cost budget and, after each step, the
    /// cost it received (`caps`): it adapts within the episode to what is left.
    CostBudget,
}

/// What a return-conditioned policy aims for when it is scored at `cost_threshold` (unscaled returns).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReturnTarget {
    pub cost_threshold: f64,
    pub reward_return: f64,
    pub cost_return: f64,
}

impl Conditioning {
    /// The threshold a per-threshold checkpoint is for; `None` for one scored at every threshold.
    pub fn cost_threshold(&self) -> Option<f64> {
        match self {
            Conditioning::PerThreshold { cost_threshold } => Some(*cost_threshold),
            _ => None,
        }
    }

    /// The `kind` in `policy.json`.
    pub fn kind(&self) -> &'static str {
        match self {
            Conditioning::Unconditioned => "unconditioned",
            Conditioning::PerThreshold { .. } => "per_threshold",
            Conditioning::TargetCost => "target_cost",
            Conditioning::ReturnsToGo { .. } => "returns_to_go",
            Conditioning::CostBudget => "cost_budget",
        }
    }

    /// Whether the network reads the threshold (so one checkpoint serves them all).
    pub fn is_conditioned(&self) -> bool {
        matches!(
            self,
            Conditioning::TargetCost | Conditioning::ReturnsToGo { .. } | Conditioning::CostBudget
        )
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "name", rename_all = "snake_case", deny_unknown_fields)]
pub enum Architecture {
    /// [`crate::gaussian::GaussianActor`]: `actor.mu.<i>.weight|bias` and `actor.log_std`; evaluated at its mean.
    GaussianMlp {
        hidden_sizes: Vec<usize>,
        activation: Activation,
        max_action: f64,
    },
    /// OSRL's `MLPActor` (BC-All, BC-Safe): `max_action · tanh(MLP(obs))`, layers `actor.net.<i>`.
    MlpActor {
        hidden_sizes: Vec<usize>,
        activation: Activation,
        max_action: f64,
    },
    /// OSRL's `SquashedGaussianMLPActor`: a trunk `actor.trunk.<i>` with the activation after every layer, heads
    /// `actor.mu` and `actor.log_std` (single linear layers, `actor.mu.0.weight`); evaluated at
    /// `max_action · tanh(mu)`.
    SquashedGaussianMlp {
        hidden_sizes: Vec<usize>,
        activation: Activation,
        max_action: f64,
    },
    /// OSRL's BCQ-Lag actor ([`crate::bcq`]): the VAE decoder `vae.decoder.<i>` (`[obs + latent, decoder hidden..,
    /// act]`, ReLU) proposes, the perturbation network `actor.pi.<i>` (`[obs + act, hidden.., act]`, OSRL uses
    /// tanh) nudges by at most `phi · max_action`; the latent is drawn per step from a generator seeded with the
    /// episode's seed.
    BcqActor {
        hidden_sizes: Vec<usize>,
        activation: Activation,
        decoder_hidden_sizes: Vec<usize>,
        latent_dim: usize,
        phi: f64,
        max_action: f64,
    },
    /// OSRL's Constrained Decision Transformer ([`crate::cdt`]), tensors `cdt.<OSRL state_dict name>`, conditioned
    /// on returns-to-go. Reward- and cost-to-go enter the model multiplied by `reward_scale` and `cost_scale`
    /// (OSRL: 0.1 and 1); `episode_len` must cover the task's horizon.
    Cdt {
        embedding_dim: usize,
        num_layers: usize,
        num_heads: usize,
        seq_len: usize,
        episode_len: usize,
        max_action: f64,
        reward_scale: f64,
        cost_scale: f64,
        /// Embed `50 − Ĉ` instead of `Ĉ` (OSRL's configs turn this on).
        cost_transform: bool,
    },
    /// CAPS ([`crate::caps`]): policy heads on a shared trunk and reward/cost critic pairs; at each step the
    /// highest-reward head whose predicted cost fits the episode's remaining budget (conditioning `cost_budget`).
    /// The budget and the costs received enter multiplied by `cost_scale`; `gamma` and `episode_len` spread what is
    /// left of it over the remaining steps.
    Caps {
        hidden_sizes: Vec<usize>,
        num_heads: usize,
        max_action: f64,
        gamma: f64,
        episode_len: usize,
        cost_scale: f64,
    },
    /// A diffusion policy ([`crate::diffusion`], FISOR's actor): the noise-prediction network `actor.*` (learnable
    /// Fourier features of the step index, a conditioning MLP with mish, `num_blocks` residual blocks of width
    /// `hidden_dim`), run by the declared `sampler` over `candidates` actions per state; the critic ensemble of the
    /// sampler's `choice` (`cost_q.<j>.<i>` or `reward_q.<j>.<i>`, ReLU MLPs on `[obs, act]`) picks the one played.
    Diffusion {
        time_dim: usize,
        cond_sizes: Vec<usize>,
        hidden_dim: usize,
        num_blocks: usize,
        layer_norm: bool,
        critic_hidden_sizes: Vec<usize>,
        critic_members: usize,
        max_action: f64,
        sampler: DiffusionSampler,
    },
    /// A latent-variable policy ([`crate::latent`], LSPC): the VAE decoder `vae.decoder.<i>` turns `[obs, z]` into
    /// `max_action · tanh(·)`; `z` from the safety encoder `safety.*` (`latent: safety_encoder`, LSPC-O) or the
    /// clamped prior (`latent: prior`, LSPC-S), drawn from a generator seeded with the episode's seed.
    LatentPolicy {
        hidden_sizes: Vec<usize>,
        decoder_hidden_sizes: Vec<usize>,
        latent_dim: usize,
        max_latent: f64,
        latent: LatentSource,
        max_action: f64,
    },
}

/// How a diffusion policy samples: DDPM over the discrete VP schedule (`steps`, `beta_min`, `beta_max`), clipping
/// each step to [−1, 1] when `clip`, with `temperature` times the step noise; `candidates` actions per state, of
/// which `choice` picks one.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum DiffusionSampler {
    Ddpm {
        steps: usize,
        beta_min: f64,
        beta_max: f64,
        clip: bool,
        temperature: f64,
        candidates: usize,
        choice: CandidateChoice,
    },
}

/// Which candidate a diffusion policy plays.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CandidateChoice {
    /// The lowest `max_j cost_q_j(s, a)` (FISOR's `minqc`: the most feasible).
    MinCostQ,
    /// The highest `min_j reward_q_j(s, a)` (IDQL-style).
    MaxRewardQ,
}

impl CandidateChoice {
    /// The prefix of the ranking critic's tensors.
    pub fn critic_prefix(self) -> &'static str {
        match self {
            CandidateChoice::MinCostQ => "cost_q",
            CandidateChoice::MaxRewardQ => "reward_q",
        }
    }
}

/// Where the latent comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LatentSource {
    /// The safety encoder's squashed Gaussian (LSPC-O).
    SafetyEncoder,
    /// The VAE prior `N(0, I)` clamped to `±max_latent` (LSPC-S).
    Prior,
}

/// The most denoising steps and candidates a sampler may declare (FISOR: 5 and 16); the step cost bounds their
/// product with the network's size.
pub const MAX_SAMPLER_STEPS: usize = 1000;
pub const MAX_SAMPLER_CANDIDATES: usize = 1024;

impl Architecture {
    /// The `name` in `policy.json`.
    pub fn name(&self) -> &'static str {
        match self {
            Architecture::GaussianMlp { .. } => "gaussian_mlp",
            Architecture::MlpActor { .. } => "mlp_actor",
            Architecture::SquashedGaussianMlp { .. } => "squashed_gaussian_mlp",
            Architecture::BcqActor { .. } => "bcq_actor",
            Architecture::Cdt { .. } => "cdt",
            Architecture::Caps { .. } => "caps",
            Architecture::Diffusion { .. } => "diffusion",
            Architecture::LatentPolicy { .. } => "latent_policy",
        }
    }
}

impl Architecture {
    /// Refuses declared constants no network can act with (a zero latent size, a discount outside [0, 1], a
    /// sampler of no steps, a scale that is not finite), naming the architecture and what each constant must be.
    /// Sizes are bounded by [`Architecture::check_step_cost`] and the weights' shapes.
    pub fn check_constants(&self) -> Result<()> {
        let refuse = |message: String| Err(PolicyError::Format(message));
        match self {
            Architecture::GaussianMlp { .. }
            | Architecture::MlpActor { .. }
            | Architecture::SquashedGaussianMlp { .. } => Ok(()),
            Architecture::BcqActor { latent_dim, phi, .. } => {
                if *latent_dim == 0 || *latent_dim > 1 << 16 || !phi.is_finite() || *phi < 0.0 {
                    return refuse("bcq_actor: latent_dim must be in 1..=65536 and phi finite and >= 0".into());
                }
                Ok(())
            }
            Architecture::Cdt {
                reward_scale,
                cost_scale,
                ..
            } => {
                if !(reward_scale.is_finite() && cost_scale.is_finite()) {
                    return refuse("cdt: reward_scale and cost_scale must be finite".into());
                }
                Ok(())
            }
            Architecture::Caps {
                gamma,
                episode_len,
                cost_scale,
                ..
            } => {
                if !(gamma.is_finite() && (0.0..=1.0).contains(gamma) && cost_scale.is_finite() && *episode_len > 0) {
                    return refuse("caps: gamma must be in [0, 1], cost_scale finite and episode_len positive".into());
                }
                Ok(())
            }
            Architecture::Diffusion {
                critic_members,
                max_action,
                sampler:
                    DiffusionSampler::Ddpm {
                        steps,
                        beta_min,
                        beta_max,
                        temperature,
                        candidates,
                        ..
                    },
                ..
            } => {
                let constants_ok = (1..=MAX_SAMPLER_STEPS).contains(steps)
                    && (1..=MAX_SAMPLER_CANDIDATES).contains(candidates)
                    && (1..=16).contains(critic_members)
                    && beta_min.is_finite()
                    && beta_max.is_finite()
                    && *beta_min >= 0.0
                    && beta_max >= beta_min
                    && temperature.is_finite()
                    && *temperature >= 0.0
                    && max_action.is_finite();
                if !constants_ok {
                    return refuse(format!(
                        "diffusion: steps must be in 1..={MAX_SAMPLER_STEPS}, candidates in \
                         1..={MAX_SAMPLER_CANDIDATES}, critic_members in 1..=16, 0 <= beta_min <= beta_max, \
                         temperature >= 0 and every constant finite"
                    ));
                }
                Ok(())
            }
            Architecture::LatentPolicy {
                latent_dim, max_latent, ..
            } => {
                if *latent_dim == 0 || *latent_dim > 1 << 16 || !(max_latent.is_finite() && *max_latent > 0.0) {
                    return refuse(
                        "latent_policy: latent_dim must be in 1..=65536 and max_latent positive and finite".into(),
                    );
                }
                Ok(())
            }
        }
    }
}

/// What one action costs one environment, computed from the declared sizes alone (before any weight is read).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepCost {
    /// Multiply-adds of one forward pass.
    pub multiply_adds: u64,
    /// The largest intermediate the forward pass holds at once: a CDT's attention scores (`heads x (4 seq_len)^2`
    /// floats per layer) or its MLP activations; an MLP's widest layer.
    pub peak_bytes: u64,
}

/// The per-environment, per-step budget a submitted architecture must fit. OSRL's CDT (embedding 128, 3 layers,
/// 8 heads, seq_len 10) needs ~25M multiply-adds and holds at most 82 kB at once (its MLP activations); the budget allows ten times the
/// arithmetic (a seq_len up to ~64 at that width) and 16 MB of scores. The evaluator plays up to 15 environments at
/// once, so a policy that fits stays within a few GFLOP per step and ~240 MB.
pub const MAX_STEP_MULTIPLY_ADDS: u64 = 250_000_000;
pub const MAX_STEP_PEAK_BYTES: u64 = 16 << 20;

impl Architecture {
    /// [`StepCost`] for a network reading `input_dim` features and producing `act_dim` actions.
    pub fn step_cost(&self, input_dim: usize, act_dim: usize) -> StepCost {
        // In f64: declared sizes are untrusted and the products of absurd ones must not overflow (they become
        // large or infinite, and the cast back saturates).
        let f = |x: usize| x as f64;
        let chain = |first: usize, hidden: &[usize], last: usize| -> (f64, f64) {
            let mut sizes = vec![first];
            sizes.extend_from_slice(hidden);
            sizes.push(last);
            let macs = sizes.windows(2).map(|w| f(w[0]) * f(w[1])).sum();
            let widest = sizes.iter().copied().max().map_or(0.0, f) * 4.0;
            (macs, widest)
        };
        let (macs, peak) = match self {
            Architecture::GaussianMlp { hidden_sizes, .. } | Architecture::MlpActor { hidden_sizes, .. } => {
                chain(input_dim, hidden_sizes, act_dim)
            }
            Architecture::SquashedGaussianMlp { hidden_sizes, .. } => {
                let (m, p) = chain(input_dim, hidden_sizes, act_dim);
                (m + hidden_sizes.last().map_or(0.0, |&h| f(h) * f(act_dim)), p)
            }
            Architecture::BcqActor {
                hidden_sizes,
                decoder_hidden_sizes,
                latent_dim,
                ..
            } => {
                let (m1, p1) = chain(input_dim.saturating_add(*latent_dim), decoder_hidden_sizes, act_dim);
                let (m2, p2) = chain(input_dim + act_dim, hidden_sizes, act_dim);
                (m1 + m2, p1.max(p2))
            }
            Architecture::Cdt {
                embedding_dim,
                num_layers,
                num_heads,
                seq_len,
                ..
            } => {
                let (d, n) = (f(*embedding_dim), 4.0 * f(*seq_len));
                let embed = f(*seq_len) * d * (f(input_dim) + f(act_dim) + 2.0);
                // Per layer: Q, K, V and the output projection (4 n d^2), the 4x MLP (8 n d^2), scores and mixing
                // (2 n^2 d).
                let layers = f(*num_layers) * (12.0 * n * d * d + 2.0 * n * n * d);
                let scores = f(*num_heads) * n * n * 4.0;
                (embed + layers + d * f(act_dim), scores.max(n * 4.0 * d * 4.0))
            }
            Architecture::Caps {
                hidden_sizes,
                num_heads,
                ..
            } => {
                // The trunk, every head, and four critics on every head's action.
                let (trunk, p1) = chain(input_dim, hidden_sizes, 0);
                let heads = f(*num_heads) * hidden_sizes.last().map_or(0.0, |&h| f(h) * f(act_dim));
                let (critic, p2) = chain(input_dim + act_dim, hidden_sizes, 1);
                (trunk + heads + 4.0 * f(*num_heads) * critic, p1.max(p2) * f(*num_heads))
            }
            Architecture::Diffusion {
                time_dim,
                cond_sizes,
                hidden_dim,
                num_blocks,
                critic_hidden_sizes,
                critic_members,
                sampler: DiffusionSampler::Ddpm { steps, candidates, .. },
                ..
            } => {
                // Every candidate through every denoising step, then through every ranking critic.
                let net = noise_net_multiply_adds(input_dim, act_dim, *time_dim, cond_sizes, *hidden_dim, *num_blocks);
                let (critic, p) = chain(input_dim.saturating_add(act_dim), critic_hidden_sizes, 1);
                let n = f(*candidates);
                (
                    n * (f(*steps) * net + f(*critic_members) * critic),
                    n * (4.0 * f(*hidden_dim) * 4.0).max(p),
                )
            }
            Architecture::LatentPolicy {
                hidden_sizes,
                decoder_hidden_sizes,
                latent_dim,
                latent,
                ..
            } => {
                // The decoder, and the safety encoder's trunk and heads when it supplies the latent.
                let (decoder, _) = chain(input_dim.saturating_add(*latent_dim), decoder_hidden_sizes, act_dim);
                let encoder = match latent {
                    LatentSource::SafetyEncoder => chain(input_dim, hidden_sizes, latent_dim.saturating_mul(2)).0,
                    LatentSource::Prior => 0.0,
                };
                let widest = hidden_sizes
                    .iter()
                    .chain(decoder_hidden_sizes)
                    .copied()
                    .max()
                    .unwrap_or(0);
                (decoder + encoder, f(widest) * 4.0)
            }
        };
        StepCost {
            multiply_adds: macs as u64,
            peak_bytes: peak as u64,
        }
    }

    /// Refuses an architecture whose [`StepCost`] is over the budget, saying by how much.
    pub fn check_step_cost(&self, input_dim: usize, act_dim: usize) -> Result<()> {
        let cost = self.step_cost(input_dim, act_dim);
        if cost.multiply_adds > MAX_STEP_MULTIPLY_ADDS || cost.peak_bytes > MAX_STEP_PEAK_BYTES {
            return Err(PolicyError::Format(format!(
                "{}: one action costs {} multiply-adds and holds {} bytes at once per environment; the evaluator's \
                 budget is {MAX_STEP_MULTIPLY_ADDS} multiply-adds and {MAX_STEP_PEAK_BYTES} bytes (for a cdt: \
                 lower seq_len, embedding_dim or num_heads)",
                self.name(),
                cost.multiply_adds,
                cost.peak_bytes
            )));
        }
        Ok(())
    }
}

/// Multiply-adds of one pass of a `diffusion` noise network for one row ([`crate::diffusion::NoiseNet`]): the time
/// features, the conditioning MLP, the input layer, each block's 4x expansion and projection, the output.
fn noise_net_multiply_adds(
    obs_dim: usize,
    act_dim: usize,
    time_dim: usize,
    cond_sizes: &[usize],
    hidden_dim: usize,
    num_blocks: usize,
) -> f64 {
    let f = |x: usize| x as f64;
    let mut macs = f(time_dim / 2);
    let mut width = time_dim;
    for &size in cond_sizes {
        macs += f(width) * f(size);
        width = size;
    }
    let h = f(hidden_dim);
    macs += (f(act_dim) + f(obs_dim) + f(width)) * h;
    macs += f(num_blocks) * 8.0 * h * h;
    macs + h * f(act_dim)
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObservationNormalization {
    pub mean: Vec<f32>,
    pub std: Vec<f32>,
}

/// Writes `policy.safetensors` and `policy.json` into `dir` (each through a temporary name and a rename, weights
/// first, so a folder with a `policy.json` is complete).
pub fn write(dir: &Path, config: &PolicyConfig, tensors: &[(String, Tensor)]) -> Result<()> {
    let io = |path: &Path| {
        let path = path.display().to_string();
        move |source| PolicyError::Io { path, source }
    };
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let weights = dir.join(WEIGHTS_FILE);
    let part = dir.join(format!("{WEIGHTS_FILE}.part"));
    // Weights are written from the CPU whatever device trained them, so a checkpoint is the same file either way.
    let map: HashMap<String, Tensor> = tensors
        .iter()
        .map(|(name, t)| Ok((name.clone(), t.to_device(&candle_core::Device::Cpu)?)))
        .collect::<Result<_>>()?;
    candle_core::safetensors::save(&map, &part)?;
    std::fs::rename(&part, &weights).map_err(io(&weights))?;
    let json = dir.join(CONFIG_FILE);
    let part = dir.join(format!("{CONFIG_FILE}.part"));
    let text = serde_json::to_vec_pretty(config).map_err(|e| PolicyError::Format(e.to_string()))?;
    std::fs::write(&part, text).map_err(io(&part))?;
    std::fs::rename(&part, &json).map_err(io(&json))?;
    Ok(())
}

fn read_limited(path: &Path, limit: u64) -> Result<Vec<u8>> {
    let io = |source| PolicyError::Io {
        path: path.display().to_string(),
        source,
    };
    let file = std::fs::File::open(path).map_err(io)?;
    let mut bytes = Vec::new();
    file.take(limit + 1).read_to_end(&mut bytes).map_err(io)?;
    if bytes.len() as u64 > limit {
        return Err(PolicyError::Format(format!(
            "{} is larger than the {limit}-byte limit",
            path.display()
        )));
    }
    Ok(bytes)
}

/// Checks a safetensors file's header before any tensor is built: its length, the tensor count, names, dtypes
/// (float32 only), ranks, and that each tensor's byte range holds exactly its declared shape inside the file. A
/// hostile header (say 900,000 zero-size tensors) is refused after reading at most [`MAX_HEADER_BYTES`], in time
/// proportional to that, instead of after building every tensor.
pub fn check_header(bytes: &[u8]) -> Result<()> {
    let bad = |why: String| PolicyError::Format(format!("{WEIGHTS_FILE} is not a valid safetensors file: {why}"));
    let Some(length) = bytes.get(..8) else {
        return Err(bad("shorter than its 8-byte header length".into()));
    };
    let length = u64::from_le_bytes(length.try_into().expect("8 bytes"));
    if length > MAX_HEADER_BYTES {
        return Err(bad(format!(
            "its header declares {length} bytes, more than the {MAX_HEADER_BYTES} allowed"
        )));
    }
    let header = bytes
        .get(8..8 + length as usize)
        .ok_or_else(|| bad(format!("the file ends inside its {length}-byte header")))?;
    let data_len = (bytes.len() - 8 - length as usize) as u64;
    // Count the entries before decoding them: a flat scan for the `"dtype"` keys bounds the work.
    let declared = header.windows(7).filter(|w| w == b"\"dtype\"").count();
    if declared > MAX_TENSORS {
        return Err(PolicyError::Format(format!(
            "{WEIGHTS_FILE} holds {declared} tensors, more than the {MAX_TENSORS} allowed"
        )));
    }
    #[derive(Deserialize)]
    struct Entry {
        dtype: String,
        shape: Vec<u64>,
        data_offsets: [u64; 2],
    }
    let entries: serde_json::Map<String, serde_json::Value> =
        serde_json::from_slice(header).map_err(|e| bad(format!("its header is not a JSON object: {e}")))?;
    let tensors = entries.iter().filter(|(name, _)| *name != "__metadata__").count();
    if tensors > MAX_TENSORS {
        return Err(PolicyError::Format(format!(
            "{WEIGHTS_FILE} holds {tensors} tensors, more than the {MAX_TENSORS} allowed"
        )));
    }
    for (name, value) in entries {
        if name == "__metadata__" {
            continue;
        }
        if name.is_empty() || name.len() > MAX_TENSOR_NAME || name.chars().any(char::is_control) {
            return Err(bad(format!(
                "tensor name {:?} is empty, longer than {MAX_TENSOR_NAME} bytes or holds control characters",
                name.chars().take(64).collect::<String>()
            )));
        }
        let entry: Entry = serde_json::from_value(value).map_err(|e| bad(format!("tensor {name:?}: {e}")))?;
        if entry.dtype != "F32" {
            return Err(PolicyError::Format(format!(
                "{WEIGHTS_FILE}: tensor {name:?} is {}, the policy format holds float32 (F32) tensors",
                entry.dtype
            )));
        }
        if entry.shape.len() > MAX_TENSOR_RANK {
            return Err(bad(format!(
                "tensor {name:?} has rank {}, more than {MAX_TENSOR_RANK}",
                entry.shape.len()
            )));
        }
        let bytes_needed = entry
            .shape
            .iter()
            .try_fold(4u64, |acc, &d| acc.checked_mul(d))
            .ok_or_else(|| bad(format!("tensor {name:?}: its shape overflows")))?;
        let [start, end] = entry.data_offsets;
        if start > end || end > data_len || end - start != bytes_needed {
            return Err(bad(format!(
                "tensor {name:?}: shape {:?} needs {bytes_needed} bytes, its offsets [{start}, {end}] do not hold \
                 them inside the {data_len} data bytes",
                entry.shape
            )));
        }
    }
    Ok(())
}

/// Parses safetensors bytes into named tensors: the header is checked first ([`check_header`]).
pub fn parse_weights(bytes: &[u8]) -> Result<HashMap<String, Tensor>> {
    check_header(bytes)?;
    let tensors = candle_core::safetensors::load_buffer(bytes, &Device::Cpu)
        .map_err(|e| PolicyError::Format(format!("{WEIGHTS_FILE} is not a valid safetensors file: {e}")))?;
    if tensors.len() > MAX_TENSORS {
        return Err(PolicyError::Format(format!(
            "{WEIGHTS_FILE} holds {} tensors, more than the {MAX_TENSORS} allowed",
            tensors.len()
        )));
    }
    // A non-finite weight makes every action it touches NaN (or, behind a ReLU in a framework that drops NaN, a
    // silent zero): refused here, with the tensor named.
    let mut names: Vec<&String> = tensors.keys().collect();
    names.sort();
    for name in names {
        let values = tensors[name]
            .to_dtype(candle_core::DType::F32)
            .and_then(|t| t.flatten_all())
            .and_then(|t| t.to_vec1::<f32>())
            .map_err(|e| PolicyError::Format(format!("{WEIGHTS_FILE}: tensor {name}: {e}")))?;
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(PolicyError::Format(format!(
                "{WEIGHTS_FILE}: tensor {name} holds a non-finite value ({} at flat index {i}); every weight must be \
                 finite",
                values[i]
            )));
        }
    }
    Ok(tensors)
}

/// Parses `policy.json` bytes (size-limited) and checks the format name.
pub fn parse_config(bytes: &[u8]) -> Result<PolicyConfig> {
    if bytes.len() as u64 > MAX_CONFIG_BYTES {
        return Err(PolicyError::Format(format!(
            "{CONFIG_FILE} is larger than the {MAX_CONFIG_BYTES}-byte limit"
        )));
    }
    let config: PolicyConfig =
        serde_json::from_slice(bytes).map_err(|e| PolicyError::Format(format!("{CONFIG_FILE}: {e}")))?;
    if config.format != FORMAT {
        return Err(PolicyError::Format(format!(
            "{CONFIG_FILE}: format is {:?}, this service reads {FORMAT:?}",
            config.format
        )));
    }
    Ok(config)
}

/// The leaderboard's digest of a submission's checkpoints, `(policy.json, weights bytes)` each: its dedupe key, and
/// the digest a scored entry records. sha256 over each checkpoint's config without its free-form `training` record
/// (re-serialized, so the JSON's formatting does not count) and its weights' bytes, each part prefixed by its
/// length, in cost-threshold order. The same network submitted twice has the same digest; so has the same network
/// trained again, whatever its training record says of time or commit.
pub fn submission_digest(checkpoints: &[(&PolicyConfig, &[u8])]) -> String {
    let mut ordered = checkpoints.to_vec();
    let key = |c: &PolicyConfig| c.conditioning.cost_threshold().unwrap_or(f64::NEG_INFINITY);
    ordered.sort_by(|a, b| key(a.0).total_cmp(&key(b.0)));
    let mut digest = Sha256::new();
    for (config, weights) in ordered {
        let canonical = serde_json::to_vec(&PolicyConfig {
            training: None,
            ..config.clone()
        })
        .expect("a PolicyConfig always serializes");
        for part in [&canonical[..], weights] {
            digest.update((part.len() as u64).to_le_bytes());
            digest.update(part);
        }
    }
    hex::encode(digest.finalize())
}

/// Reads a checkpoint folder's `policy.json` and the bytes of its weights, both size-limited, as
/// [`submission_digest`] takes them.
pub fn read_bytes(dir: &Path) -> Result<(PolicyConfig, Vec<u8>)> {
    let config = parse_config(&read_limited(&dir.join(CONFIG_FILE), MAX_CONFIG_BYTES)?)?;
    Ok((config, read_limited(&dir.join(WEIGHTS_FILE), MAX_WEIGHTS_BYTES)?))
}

/// Reads a checkpoint folder's config and weights.
pub fn read(dir: &Path) -> Result<(PolicyConfig, HashMap<String, Tensor>)> {
    let (config, weights) = read_bytes(dir)?;
    Ok((config, parse_weights(&weights)?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_noise_networks_multiply_adds_are_its_weight_count() {
        // One multiply-add per weight of each linear layer (and per time-kernel entry) for each row.
        let shape = crate::diffusion::DiffusionShape {
            obs_dim: 7,
            act_dim: 2,
            time_dim: 8,
            cond_sizes: vec![16, 12],
            hidden_dim: 10,
            num_blocks: 3,
            layer_norm: true,
        };
        let net = crate::diffusion::NoiseNet::new(shape, &mut crate::noise::Noise::seeded(1)).unwrap();
        let weights: usize = net
            .named_vars("a")
            .iter()
            .filter(|(name, _)| name.ends_with(".weight") && !name.contains(".norm.") || name.ends_with("kernel"))
            .map(|(_, v)| v.elem_count())
            .sum();
        assert_eq!(noise_net_multiply_adds(7, 2, 8, &[16, 12], 10, 3), weights as f64);
    }
    use crate::Policy;
    use crate::gaussian::{GaussianActor, matrix};
    use crate::noise::Noise;

    fn config() -> PolicyConfig {
        PolicyConfig {
            format: FORMAT.into(),
            task: "OfflineBallRun-v0".into(),
            obs_dim: 7,
            act_dim: 2,
            architecture: Architecture::GaussianMlp {
                hidden_sizes: vec![32, 32],
                activation: Activation::Tanh,
                max_action: 1.0,
            },
            observation_normalization: None,
            conditioning: Conditioning::Unconditioned,
            training: None,
        }
    }

    #[test]
    fn a_written_checkpoint_reads_back_to_the_same_actions() {
        let actor = GaussianActor::new(7, 2, &[32, 32], Activation::Tanh, 1.0, &mut Noise::seeded(2)).unwrap();
        let tensors = crate::tensors_of(actor.named_vars());
        let dir = tempfile::tempdir().unwrap();
        write(dir.path(), &config(), &tensors).unwrap();
        let (back_config, back_tensors) = read(dir.path()).unwrap();
        assert_eq!(back_config, config());
        let policy = Policy::load(&back_config, &back_tensors).unwrap();
        let obs = matrix(&[0.1, -0.2, 0.3, 0.0, 1.0, 2.0, -1.0], 1, 7).unwrap();
        let want = actor
            .mean(&obs)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert_eq!(policy.act(&obs).unwrap(), want);

        // A config that disagrees with the weights is refused with the reason.
        let mut wrong = config();
        wrong.obs_dim = 8;
        let err = Policy::load(&wrong, &back_tensors).err().unwrap().to_string();
        assert!(err.contains("layer sizes [7, 32, 32, 2]"), "{err}");
        // Bytes that are not safetensors are refused, not a panic.
        std::fs::write(
            dir.path().join(WEIGHTS_FILE),
            b"\xff\xff\xff\xff\xff\xff\xff\x7fnot a header",
        )
        .unwrap();
        let err = read(dir.path()).err().unwrap().to_string();
        assert!(err.contains("not a valid safetensors file"), "{err}");
    }

    /// A safetensors file with the given JSON header and data bytes.
    fn safetensors(header: &str, data: &[u8]) -> Vec<u8> {
        let mut bytes = (header.len() as u64).to_le_bytes().to_vec();
        bytes.extend_from_slice(header.as_bytes());
        bytes.extend_from_slice(data);
        bytes
    }

    fn cdt(seq_len: usize, num_heads: usize) -> Architecture {
        Architecture::Cdt {
            embedding_dim: 128,
            num_layers: 3,
            num_heads,
            seq_len,
            episode_len: 1000,
            max_action: 1.0,
            reward_scale: 0.1,
            cost_scale: 1.0,
            cost_transform: true,
        }
    }

    #[test]
    fn declared_constants_no_network_can_act_with_are_refused_by_name() {
        // Each architecture as a policy.json declares it, with sound constants; then one constant made unusable
        // (infinity included, which JSON cannot carry but a config built in code can).
        let declared = [
            r#"{"name":"bcq_actor","hidden_sizes":[8],"activation":"tanh","decoder_hidden_sizes":[8],
                "latent_dim":4,"phi":0.05,"max_action":1.0}"#,
            r#"{"name":"cdt","embedding_dim":8,"num_layers":1,"num_heads":1,"seq_len":2,"episode_len":10,
                "max_action":1.0,"reward_scale":0.1,"cost_scale":1.0,"cost_transform":true}"#,
            r#"{"name":"caps","hidden_sizes":[8],"num_heads":2,"max_action":1.0,"gamma":0.99,"episode_len":10,
                "cost_scale":1.0}"#,
            r#"{"name":"diffusion","time_dim":4,"cond_sizes":[8],"hidden_dim":8,"num_blocks":1,"layer_norm":true,
                "critic_hidden_sizes":[8],"critic_members":2,"max_action":1.0,
                "sampler":{"kind":"ddpm","steps":5,"beta_min":0.1,"beta_max":10.0,"clip":true,"temperature":0.0,
                "candidates":4,"choice":"min_cost_q"}}"#,
            r#"{"name":"latent_policy","hidden_sizes":[8],"decoder_hidden_sizes":[8],"latent_dim":4,
                "max_latent":0.25,"latent":"prior","max_action":1.0}"#,
        ];
        let mut refused = 0;
        for json in declared {
            let sound: Architecture = serde_json::from_str(json).unwrap();
            sound.check_constants().unwrap();
            let mut breaks: Vec<(&str, Architecture)> = Vec::new();
            let mut with = |field, change: &dyn Fn(&mut Architecture)| {
                let mut broken = sound.clone();
                change(&mut broken);
                breaks.push((field, broken));
            };
            match &sound {
                Architecture::BcqActor { .. } => {
                    with("latent_dim", &|a| {
                        if let Architecture::BcqActor { latent_dim, .. } = a {
                            *latent_dim = 0
                        }
                    });
                    with("phi", &|a| {
                        if let Architecture::BcqActor { phi, .. } = a {
                            *phi = -0.1
                        }
                    });
                }
                Architecture::Cdt { .. } => {
                    with("reward_scale", &|a| {
                        if let Architecture::Cdt { reward_scale, .. } = a {
                            *reward_scale = f64::INFINITY
                        }
                    });
                    with("cost_scale", &|a| {
                        if let Architecture::Cdt { cost_scale, .. } = a {
                            *cost_scale = f64::NAN
                        }
                    });
                }
                Architecture::Caps { .. } => {
                    with("gamma", &|a| {
                        if let Architecture::Caps { gamma, .. } = a {
                            *gamma = 1.5
                        }
                    });
                    with("episode_len", &|a| {
                        if let Architecture::Caps { episode_len, .. } = a {
                            *episode_len = 0
                        }
                    });
                }
                Architecture::Diffusion { .. } => {
                    let sampler = |a: &mut Architecture, f: &dyn Fn(&mut usize, &mut f64)| {
                        if let Architecture::Diffusion {
                            sampler: DiffusionSampler::Ddpm { steps, beta_min, .. },
                            ..
                        } = a
                        {
                            f(steps, beta_min)
                        }
                    };
                    with("steps", &|a| sampler(a, &|steps, _| *steps = 0));
                    with("beta_min", &|a| sampler(a, &|_, beta_min| *beta_min = 20.0));
                    with("critic_members", &|a| {
                        if let Architecture::Diffusion { critic_members, .. } = a {
                            *critic_members = 17
                        }
                    });
                }
                Architecture::LatentPolicy { .. } => {
                    with("max_latent", &|a| {
                        if let Architecture::LatentPolicy { max_latent, .. } = a {
                            *max_latent = -1.0
                        }
                    });
                }
                other => panic!("{} has no constants to break", other.name()),
            }
            for (field, broken) in breaks {
                let err = broken.check_constants().unwrap_err().to_string();
                assert!(err.contains(sound.name()) && err.contains(field), "{field}: {err}");
                refused += 1;
            }
        }
        assert_eq!(refused, 10);
        // Sizes and activations alone: nothing to refuse.
        let mlp: Architecture =
            serde_json::from_str(r#"{"name":"mlp_actor","hidden_sizes":[],"activation":"relu","max_action":1.0}"#)
                .unwrap();
        mlp.check_constants().unwrap();
    }

    #[test]
    fn the_step_budget_admits_osrls_networks_and_refuses_runaway_contexts() {
        // OSRL's CDT defaults, worked by hand: 40 tokens, 3 x (12 x 40 x 128^2 + 2 x 40^2 x 128) plus embeddings
        // 10 x 128 x (60 + 2 + 2) and the head 128 x 2.
        let cost = cdt(10, 8).step_cost(60, 2);
        assert_eq!(
            cost.multiply_adds,
            3 * (12 * 40 * 128 * 128 + 2 * 40 * 40 * 128) + 10 * 128 * 64 + 128 * 2
        );
        // Its widest activation (40 tokens x the 4x MLP's 512 floats) is larger than its 8 x 40 x 40 scores.
        assert_eq!(cost.peak_bytes, 40 * 512 * 4);
        cdt(10, 8).check_step_cost(60, 2).unwrap();
        // The outside probe's submission: seq_len 1000 on a 1000-step task (tens of GB of scores at 8 heads).
        let err = cdt(1000, 8).check_step_cost(60, 2).unwrap_err().to_string();
        assert!(err.contains("lower seq_len"), "{err}");
        // BC's MLP [256, 256] on the widest task.
        let mlp = Architecture::MlpActor {
            hidden_sizes: vec![256, 256],
            activation: Activation::Relu,
            max_action: 1.0,
        };
        assert_eq!(mlp.step_cost(259, 2).multiply_adds, 259 * 256 + 256 * 256 + 256 * 2);
        mlp.check_step_cost(259, 2).unwrap();
        // Declared sizes far past any weights file cannot overflow the arithmetic.
        let absurd = Architecture::MlpActor {
            hidden_sizes: vec![usize::MAX, usize::MAX],
            activation: Activation::Relu,
            max_action: 1.0,
        };
        assert!(absurd.check_step_cost(8, 2).is_err());
    }

    #[test]
    fn hostile_weights_are_refused_without_allocating_what_they_declare() {
        // A header length of 2^60 bytes.
        let mut huge_header = (1u64 << 60).to_le_bytes().to_vec();
        huge_header.extend_from_slice(b"{}");
        // A tensor declared as 10^9 x 10^9 floats over 16 bytes of data.
        let huge_tensor = safetensors(
            r#"{"w":{"dtype":"F32","shape":[1000000000,1000000000],"data_offsets":[0,16]}}"#,
            &[0; 16],
        );
        // Offsets past the end of the data.
        let past_end = safetensors(r#"{"w":{"dtype":"F32","shape":[4],"data_offsets":[0,64]}}"#, &[0; 16]);
        for (name, bytes) in [
            ("huge header", huge_header),
            ("huge tensor", huge_tensor),
            ("past end", past_end),
            ("truncated", vec![1, 2, 3]),
        ] {
            let err = parse_weights(&bytes)
                .err()
                .unwrap_or_else(|| panic!("{name} was accepted"));
            assert!(
                err.to_string().contains("not a valid safetensors file"),
                "{name}: {err}"
            );
        }
        // Too many tensors.
        let entries: Vec<String> = (0..=MAX_TENSORS)
            .map(|i| {
                format!(
                    r#""t{i}":{{"dtype":"F32","shape":[1],"data_offsets":[{},{}]}}"#,
                    4 * i,
                    4 * i + 4
                )
            })
            .collect();
        let many = safetensors(&format!("{{{}}}", entries.join(",")), &vec![0; 4 * (MAX_TENSORS + 1)]);
        let err = parse_weights(&many).err().unwrap().to_string();
        assert!(err.contains("more than the 256 allowed"), "{err}");
        // The outside probe's stall: 900,000 zero-size tensors (a 53 MB file) took ~4.8 s to refuse because
        // every tensor was built first. Its header is refused by length before it is parsed; one that fits the
        // header limit is refused by its count.
        let zero: Vec<String> = (0..900_000)
            .map(|i| format!(r#""z{i}":{{"dtype":"F32","shape":[0],"data_offsets":[0,0]}}"#))
            .collect();
        let stall = safetensors(&format!("{{{}}}", zero.join(",")), &[]);
        let started = std::time::Instant::now();
        let err = parse_weights(&stall).err().unwrap().to_string();
        assert!(err.contains("more than the 262144 allowed"), "{err}");
        assert!(
            started.elapsed() < std::time::Duration::from_millis(100),
            "{:?}",
            started.elapsed()
        );
        let few_zero = safetensors(&format!("{{{}}}", zero[..3000].join(",")), &[]);
        let err = parse_weights(&few_zero).err().unwrap().to_string();
        assert!(err.contains("holds 3000 tensors, more than the 256 allowed"), "{err}");
        // Other dtypes, names, ranks and inconsistent offsets are named.
        for (header, data, expected) in [
            (r#"{"w":{"dtype":"F64","shape":[1],"data_offsets":[0,8]}}"#, 8, "is F64"),
            (
                r#"{"w":{"dtype":"F32","shape":[1,1,1,1,1],"data_offsets":[0,4]}}"#,
                4,
                "rank 5",
            ),
            (
                r#"{"w":{"dtype":"F32","shape":[2],"data_offsets":[0,4]}}"#,
                4,
                "needs 8 bytes",
            ),
            (
                r#"{"":{"dtype":"F32","shape":[1],"data_offsets":[0,4]}}"#,
                4,
                "is empty",
            ),
            (
                r#"{"w":{"dtype":"F32","shape":[4294967296,4294967296,4],"data_offsets":[0,4]}}"#,
                4,
                "overflows",
            ),
            (r#"[1,2]"#, 0, "not a JSON object"),
        ] {
            let err = parse_weights(&safetensors(header, &vec![0; data]))
                .err()
                .unwrap()
                .to_string();
            assert!(err.contains(expected), "{header}: {err}");
        }
        // Files over the limit are not read whole.
        let dir = tempfile::tempdir().unwrap();
        let big = dir.path().join("big");
        std::fs::write(&big, vec![0u8; 2048]).unwrap();
        let err = read_limited(&big, 1024).err().unwrap().to_string();
        assert!(err.contains("larger than the 1024-byte limit"), "{err}");
        assert_eq!(read_limited(&big, 4096).unwrap().len(), 2048);
    }
}
