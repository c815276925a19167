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
}

impl Architecture {
    /// The `name` in `policy.json`.
    pub fn name(&self) -> &'static str {
        match self {
            Architecture::GaussianMlp { .. } => "gaussian_mlp",
            Architecture::MlpActor { .. } => "mlp_actor",
            Architecture::SquashedGaussianMlp { .. } => "squashed_gaussian_mlp",
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
}

/// Checks that an MLP's layer sizes are `[obs_dim, hidden.., out]`.
fn check_sizes(name: &str, net: &Mlp, want: Vec<usize>) -> Result<()> {
    let sizes = net.sizes();
    if sizes != want {
        return Err(PolicyError::Format(format!(
            "{name} has layer sizes {sizes:?}, but {CONFIG_FILE} declares {want:?}"
        )));
    }
    Ok(())
}

fn layer_sizes(obs_dim: usize, hidden: &[usize], out: usize) -> Vec<usize> {
    std::iter::once(obs_dim)
        .chain(hidden.iter().copied())
        .chain([out])
        .collect()
}

/// A loaded policy, ready to act: its network and the observation normalization it declares.
pub struct Policy {
    pub network: Network,
    /// `(mean, std)` as `[1, obs_dim]` rows.
    normalization: Option<(Tensor, Tensor)>,
}

impl Policy {
    /// Builds the architecture the config declares from the weights, checking names and shapes against it.
    pub fn load(config: &PolicyConfig, tensors: &HashMap<String, Tensor>) -> Result<Policy> {
        let normalization = match &config.observation_normalization {
            None => None,
            Some(n) => {
                if n.mean.len() != config.obs_dim || n.std.len() != config.obs_dim {
                    return Err(PolicyError::Format(format!(
                        "observation_normalization needs {} means and stds, got {} and {}",
                        config.obs_dim,
                        n.mean.len(),
                        n.std.len()
                    )));
                }
                if n.std.iter().any(|s| !(s.is_finite() && *s > 0.0)) || n.mean.iter().any(|m| !m.is_finite()) {
                    return Err(PolicyError::Format(
                        "observation_normalization: every std must be positive and finite, every mean finite".into(),
                    ));
                }
                let row = |v: &[f32]| Tensor::from_slice(v, (1, v.len()), &Device::Cpu);
                Some((row(&n.mean)?, row(&n.std)?))
            }
        };
        Ok(Policy {
            network: Network::load(config, tensors)?,
            normalization,
        })
    }

    /// Deterministic actions (the mean for stochastic actors), row-major `[batch, act_dim]`.
    pub fn act(&self, obs: &Tensor) -> Result<Vec<f32>> {
        match &self.normalization {
            None => self.network.act(obs),
            Some((mean, std)) => self.network.act(&obs.broadcast_sub(mean)?.broadcast_div(std)?),
        }
    }
}

impl Network {
    fn load(config: &PolicyConfig, tensors: &HashMap<String, Tensor>) -> Result<Network> {
        match &config.architecture {
            Architecture::GaussianMlp {
                hidden_sizes,
                activation,
                max_action,
            } => {
                let mean_net = Mlp::from_tensors("actor.mu", tensors, *activation)?;
                check_sizes(
                    "actor.mu",
                    &mean_net,
                    layer_sizes(config.obs_dim, hidden_sizes, config.act_dim),
                )?;
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
                Ok(Network::Gaussian(GaussianActor {
                    mean_net,
                    log_std: candle_core::Var::from_tensor(&log_std.copy()?)?,
                    max_action: *max_action,
                }))
            }
            Architecture::MlpActor {
                hidden_sizes,
                activation,
                max_action,
            } => {
                let net = Mlp::from_tensors("actor.net", tensors, *activation)?;
                check_sizes(
                    "actor.net",
                    &net,
                    layer_sizes(config.obs_dim, hidden_sizes, config.act_dim),
                )?;
                Ok(Network::Mlp {
                    net,
                    max_action: *max_action,
                })
            }
            Architecture::SquashedGaussianMlp {
                hidden_sizes,
                activation,
                max_action,
            } => {
                let (Some(&last), false) = (hidden_sizes.last(), hidden_sizes.is_empty()) else {
                    return Err(PolicyError::Format(
                        "squashed_gaussian_mlp needs at least one hidden layer".into(),
                    ));
                };
                let trunk = Mlp::from_tensors("actor.trunk", tensors, *activation)?;
                let mut trunk_sizes = vec![config.obs_dim];
                trunk_sizes.extend(hidden_sizes);
                check_sizes("actor.trunk", &trunk, trunk_sizes)?;
                let mu = Mlp::from_tensors("actor.mu", tensors, *activation)?;
                check_sizes("actor.mu", &mu, vec![last, config.act_dim])?;
                Ok(Network::Squashed {
                    trunk,
                    mu,
                    activation: *activation,
                    max_action: *max_action,
                })
            }
        }
    }

    fn act(&self, obs: &Tensor) -> Result<Vec<f32>> {
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
        };
        Ok(out.flatten_all()?.to_vec1::<f32>()?)
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

    #[test]
    fn every_architecture_acts_as_its_definition_and_applies_the_declared_normalization() {
        let mut noise = Noise::seeded(3);
        let obs = matrix(&[0.5, -1.0, 2.0, 0.1, 0.2, 0.3], 2, 3).unwrap();
        let with = |architecture: Architecture, normalization: Option<ObservationNormalization>| PolicyConfig {
            format: FORMAT.into(),
            task: "OfflineCarRun-v0".into(),
            obs_dim: 3,
            act_dim: 2,
            architecture,
            observation_normalization: normalization,
            conditioning: Conditioning::Unconditioned,
            training: None,
        };

        // mlp_actor: 2·tanh(net(obs)).
        let net = Mlp::orthogonal("actor.net", &[3, 8, 2], Activation::Relu, 1.0, 1.0, &mut noise).unwrap();
        let config = with(
            Architecture::MlpActor {
                hidden_sizes: vec![8],
                activation: Activation::Relu,
                max_action: 2.0,
            },
            None,
        );
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
        let normalized = Policy::load(&with(config.architecture.clone(), Some(normalization)), &tensors).unwrap();
        let by_hand = matrix(&[-0.25, -1.0, 6.0, -0.45, 0.2, 2.6], 2, 3).unwrap();
        let got = normalized.act(&obs).unwrap();
        for (a, b) in got.iter().zip(policy.act(&by_hand).unwrap()) {
            assert!((a - b).abs() < 1e-6, "{got:?}");
        }
        let bad = ObservationNormalization {
            mean: vec![0.0; 3],
            std: vec![1.0, 0.0, 1.0],
        };
        let err = Policy::load(&with(config.architecture.clone(), Some(bad)), &tensors)
            .err()
            .unwrap();
        assert!(err.to_string().contains("every std must be positive"), "{err}");

        // squashed_gaussian_mlp: tanh(mu(relu(trunk(obs)))), the trunk's activation after its last layer too.
        let trunk = Mlp::orthogonal("actor.trunk", &[3, 8, 8], Activation::Relu, 1.0, 1.0, &mut noise).unwrap();
        let mu = Mlp::orthogonal("actor.mu", &[8, 2], Activation::Relu, 1.0, 1.0, &mut noise).unwrap();
        let log_std = Mlp::orthogonal("actor.log_std", &[8, 2], Activation::Relu, 1.0, 1.0, &mut noise).unwrap();
        let mut all = crate::tensors_of(trunk.named_vars());
        all.extend(crate::tensors_of(mu.named_vars()));
        all.extend(crate::tensors_of(log_std.named_vars()));
        let tensors: HashMap<String, Tensor> = all.into_iter().collect();
        let config = with(
            Architecture::SquashedGaussianMlp {
                hidden_sizes: vec![8, 8],
                activation: Activation::Relu,
                max_action: 1.0,
            },
            None,
        );
        let policy = Policy::load(&config, &tensors).unwrap();
        let h = trunk.forward(&obs).unwrap().relu().unwrap();
        let want = mu.forward(&h).unwrap().tanh().unwrap();
        assert_eq!(
            policy.act(&obs).unwrap(),
            want.flatten_all().unwrap().to_vec1::<f32>().unwrap()
        );
        let wrong = with(
            Architecture::SquashedGaussianMlp {
                hidden_sizes: vec![8, 4],
                activation: Activation::Relu,
                max_action: 1.0,
            },
            None,
        );
        let err = Policy::load(&wrong, &tensors).err().unwrap().to_string();
        assert!(err.contains("actor.trunk has layer sizes [3, 8, 8]"), "{err}");
    }
}
