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

use crate::mlp::Activation;
use crate::{PolicyError, Result};

pub const WEIGHTS_FILE: &str = "policy.safetensors";
pub const CONFIG_FILE: &str = "policy.json";
pub const FORMAT: &str = "dsrl-policy/1";
/// Largest weights file read (the paper's largest policies are well under 10 MB).
pub const MAX_WEIGHTS_BYTES: u64 = 64 << 20;
pub const MAX_CONFIG_BYTES: u64 = 64 << 10;
pub const MAX_TENSORS: usize = 256;

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
        }
    }

    /// Whether the network reads the threshold (so one checkpoint serves them all).
    pub fn is_conditioned(&self) -> bool {
        matches!(self, Conditioning::TargetCost | Conditioning::ReturnsToGo { .. })
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
}

impl Architecture {
    /// The `name` in `policy.json`.
    pub fn name(&self) -> &'static str {
        match self {
            Architecture::GaussianMlp { .. } => "gaussian_mlp",
            Architecture::MlpActor { .. } => "mlp_actor",
            Architecture::SquashedGaussianMlp { .. } => "squashed_gaussian_mlp",
            Architecture::BcqActor { .. } => "bcq_actor",
            Architecture::Cdt { .. } => "cdt",
        }
    }
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
    let map: HashMap<String, Tensor> = tensors.iter().cloned().collect();
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

/// Parses safetensors bytes into named tensors, with the tensor-count limit.
pub fn parse_weights(bytes: &[u8]) -> Result<HashMap<String, Tensor>> {
    let tensors = candle_core::safetensors::load_buffer(bytes, &Device::Cpu)
        .map_err(|e| PolicyError::Format(format!("{WEIGHTS_FILE} is not a valid safetensors file: {e}")))?;
    if tensors.len() > MAX_TENSORS {
        return Err(PolicyError::Format(format!(
            "{WEIGHTS_FILE} holds {} tensors, more than the {MAX_TENSORS} allowed",
            tensors.len()
        )));
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

/// Reads a checkpoint folder's config and weights.
pub fn read(dir: &Path) -> Result<(PolicyConfig, HashMap<String, Tensor>)> {
    let config = parse_config(&read_limited(&dir.join(CONFIG_FILE), MAX_CONFIG_BYTES)?)?;
    let tensors = parse_weights(&read_limited(&dir.join(WEIGHTS_FILE), MAX_WEIGHTS_BYTES)?)?;
    Ok((config, tensors))
}

#[cfg(test)]
mod tests {
    use super::*;
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
        // Files over the limit are not read whole.
        let dir = tempfile::tempdir().unwrap();
        let big = dir.path().join("big");
        std::fs::write(&big, vec![0u8; 2048]).unwrap();
        let err = read_limited(&big, 1024).err().unwrap().to_string();
        assert!(err.contains("larger than the 1024-byte limit"), "{err}");
        assert_eq!(read_limited(&big, 4096).unwrap().len(), 2048);
    }
}
