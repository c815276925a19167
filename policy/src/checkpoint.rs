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

use crate::gaussian::GaussianActor;
use crate::mlp::{Activation, Mlp};
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
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "name", rename_all = "snake_case", deny_unknown_fields)]
pub enum Architecture {
    /// [`GaussianActor`]: `actor.mu.<i>.weight|bias` and `actor.log_std`; evaluated at its mean.
    GaussianMlp {
        hidden_sizes: Vec<usize>,
        activation: Activation,
        max_action: f64,
    },
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

/// Reads a checkpoint folder's config and weights.
pub fn read(dir: &Path) -> Result<(PolicyConfig, HashMap<String, Tensor>)> {
    let config: PolicyConfig = serde_json::from_slice(&read_limited(&dir.join(CONFIG_FILE), MAX_CONFIG_BYTES)?)
        .map_err(|e| PolicyError::Format(format!("{CONFIG_FILE}: {e}")))?;
    if config.format != FORMAT {
        return Err(PolicyError::Format(format!(
            "{CONFIG_FILE}: format is {:?}, this service reads {FORMAT:?}",
            config.format
        )));
    }
    let tensors = parse_weights(&read_limited(&dir.join(WEIGHTS_FILE), MAX_WEIGHTS_BYTES)?)?;
    Ok((config, tensors))
}

/// A loaded policy, ready to act.
pub enum Policy {
    Gaussian(GaussianActor),
}

impl Policy {
    /// Builds the architecture the config declares from the weights, checking names and shapes against it.
    pub fn load(config: &PolicyConfig, tensors: &HashMap<String, Tensor>) -> Result<Policy> {
        match &config.architecture {
            Architecture::GaussianMlp {
                hidden_sizes,
                activation,
                max_action,
            } => {
                let mean_net = Mlp::from_tensors("actor.mu", tensors, *activation)?;
                let sizes = mean_net.sizes();
                let want: Vec<usize> = std::iter::once(config.obs_dim)
                    .chain(hidden_sizes.iter().copied())
                    .chain([config.act_dim])
                    .collect();
                if sizes != want {
                    return Err(PolicyError::Format(format!(
                        "actor.mu has layer sizes {sizes:?}, but {CONFIG_FILE} declares {want:?}"
                    )));
                }
                let log_std = tensors
                    .get("actor.log_std")
                    .ok_or_else(|| PolicyError::Format("actor.log_std is missing".into()))?;
                if log_std.dims() != [config.act_dim] {
                    return Err(PolicyError::Format(format!(
                        "actor.log_std has shape {:?}, expected [{}]",
                        log_std.dims(),
                        config.act_dim
                    )));
                }
                Ok(Policy::Gaussian(GaussianActor {
                    mean_net,
                    log_std: candle_core::Var::from_tensor(&log_std.copy()?)?,
                    max_action: *max_action,
                }))
            }
        }
    }

    /// Deterministic actions (the mean for stochastic actors), row-major `[batch, act_dim]`.
    pub fn act(&self, obs: &Tensor) -> Result<Vec<f32>> {
        match self {
            Policy::Gaussian(actor) => Ok(actor.mean(obs)?.flatten_all()?.to_vec1::<f32>()?),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gaussian::matrix;
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
        }
    }

    #[test]
    fn a_written_checkpoint_reads_back_to_the_same_actions() {
        let actor = GaussianActor::new(7, 2, &[32, 32], Activation::Tanh, 1.0, &mut Noise::seeded(2)).unwrap();
        let tensors: Vec<(String, Tensor)> = actor
            .named_vars()
            .into_iter()
            .map(|(n, v)| (n, v.as_tensor().clone()))
            .collect();
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
}
