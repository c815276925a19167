//! Reference learners trained in candle on the hosted datasets, written in the evaluator's policy format.
//!
//! BC-All and BC-Safe (OSRL `bc.py`, spec 5.5): an `MLPActor` (`[256, 256]`, ReLU, `tanh · max_action`) regressing
//! the dataset's actions with MSE, Adam lr 1e-3, batches of 512 drawn uniformly with replacement. BC-Safe keeps only
//! the episodes whose (undiscounted) cost return is at most the threshold and is trained once per threshold.
//!
//! CDT (`cdt`) is trained once and conditioned on return targets. The per-threshold offline baselines have a module each (`bcql`, `bearl`, `cpq`, `coptidice`), built on what
//! `dsrl_policy::offline`, `dsrl_policy::squashed` and `dsrl_policy::vae` share, with the sampler and learner
//! interface in `offline`.

pub mod bcql;
pub mod bearl;
pub mod caps;
pub mod cdt;
pub mod cdt_augment;
pub mod coptidice;
pub mod cpq;
pub mod fisor;
pub mod lspc;
pub mod offline;
pub mod parity;
pub mod reference;

use std::path::Path;

use anyhow::Context;
use dsrl_policy::adam::Adam;
use dsrl_policy::checkpoint::{self, Architecture, Conditioning, PolicyConfig};
use dsrl_policy::gaussian::matrix;
use dsrl_policy::mlp::{Activation, Mlp};
use dsrl_policy::noise::Noise;
use dsrl_policy::{Device, Tensor};
use dsrl_suite::parquet_file::ParquetTransitions;

/// The device `--device` names: `cpu`, `cuda` (the first GPU) or `cuda:N`. CUDA needs a binary built with the
/// `cuda` feature (scripts/build-cuda.sh); without it, or without a GPU, the error says so.
pub fn training_device(name: &str) -> anyhow::Result<Device> {
    let ordinal = match name {
        "cpu" => return Ok(Device::Cpu),
        "cuda" => 0,
        other => match other.strip_prefix("cuda:").map(str::parse::<usize>) {
            Some(Ok(n)) => n,
            _ => anyhow::bail!("--device {other:?}: the devices are cpu, cuda and cuda:N (N = 0, 1, ...)"),
        },
    };
    if !cfg!(feature = "cuda") {
        anyhow::bail!(
            "--device {name}: this dsrl-train was built without the `cuda` feature; scripts/build-cuda.sh builds \
             one (CUDA from PyPI, no system CUDA needed)"
        );
    }
    Device::new_cuda(ordinal).with_context(|| format!("--device {name}: opening GPU {ordinal}"))
}

/// How a training record names a device: `cpu` or `cuda:N`.
pub fn device_name(device: &Device) -> String {
    match device.location() {
        candle_core::DeviceLocation::Cpu => "cpu".to_owned(),
        candle_core::DeviceLocation::Cuda { gpu_id } => format!("cuda:{gpu_id}"),
        candle_core::DeviceLocation::Metal { gpu_id } => format!("metal:{gpu_id}"),
    }
}

/// Every action of the 38 tasks lies in [-1, 1].
pub const MAX_ACTION: f64 = 1.0;

/// A dataset's observations and actions with its episodes' boundaries and returns.
pub struct Demonstrations {
    pub obs_dim: usize,
    pub act_dim: usize,
    pub observations: Vec<f32>,
    pub actions: Vec<f32>,
    /// (first row, rows, reward return, cost return) per episode.
    pub episodes: Vec<(usize, usize, f64, f64)>,
    pub next_observations: Vec<f32>,
    pub rewards: Vec<f32>,
    pub costs: Vec<f32>,
    /// 1 where the episode ends (a terminal or a time limit: OSRL's `TransitionDataset` treats both as terminal).
    pub dones: Vec<f32>,
}

impl Demonstrations {
    pub fn read(path: &Path) -> anyhow::Result<Demonstrations> {
        let file = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
        let mut out: Option<Demonstrations> = None;
        let (mut start, mut rows, mut reward, mut cost) = (0usize, 0usize, 0f64, 0f64);
        for chunk in ParquetTransitions::open(file).with_context(|| format!("reading {}", path.display()))? {
            let chunk = chunk.with_context(|| format!("reading {}", path.display()))?;
            let d = out.get_or_insert_with(|| Demonstrations::empty(chunk.obs_dim, chunk.act_dim));
            d.observations.extend_from_slice(&chunk.observations);
            d.actions.extend_from_slice(&chunk.actions);
            d.next_observations.extend_from_slice(&chunk.next_observations);
            d.rewards.extend_from_slice(&chunk.rewards);
            d.costs.extend_from_slice(&chunk.costs);
            d.dones
                .extend((0..chunk.len()).map(|i| if chunk.is_done(i) { 1.0 } else { 0.0 }));
            for i in 0..chunk.len() {
                rows += 1;
                reward += f64::from(chunk.rewards[i]);
                cost += f64::from(chunk.costs[i]);
                if chunk.is_done(i) {
                    d.episodes.push((start, rows, reward, cost));
                    start += rows;
                    (rows, reward, cost) = (0, 0.0, 0.0);
                }
            }
        }
        let d = out.context("the dataset holds no transitions")?;
        anyhow::ensure!(rows == 0, "the dataset ends in the middle of an episode");
        Ok(d)
    }

    /// A dataset with no transitions yet, of these widths.
    pub fn empty(obs_dim: usize, act_dim: usize) -> Demonstrations {
        Demonstrations {
            obs_dim,
            act_dim,
            observations: Vec::new(),
            actions: Vec::new(),
            episodes: Vec::new(),
            next_observations: Vec::new(),
            rewards: Vec::new(),
            costs: Vec::new(),
            dones: Vec::new(),
        }
    }

    /// Transitions in the dataset.
    pub fn rows(&self) -> usize {
        self.rewards.len()
    }

    /// The rows of the episodes whose cost return is at most `cost_threshold` (all rows for `None`).
    pub fn select(&self, cost_threshold: Option<f64>) -> (Vec<f32>, Vec<f32>, usize) {
        let (mut obs, mut act, mut kept) = (Vec::new(), Vec::new(), 0);
        for &(start, rows, _, cost) in &self.episodes {
            if cost_threshold.is_some_and(|k| cost > k) {
                continue;
            }
            kept += 1;
            obs.extend_from_slice(&self.observations[start * self.obs_dim..(start + rows) * self.obs_dim]);
            act.extend_from_slice(&self.actions[start * self.act_dim..(start + rows) * self.act_dim]);
        }
        (obs, act, kept)
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct BcSettings {
    pub hidden_sizes: Vec<usize>,
    pub lr: f64,
    pub batch_size: usize,
    pub steps: u64,
    pub seed: u64,
}

impl Default for BcSettings {
    /// OSRL's BC configuration (100k steps; 200k for MetaDrive).
    fn default() -> Self {
        BcSettings {
            hidden_sizes: vec![256, 256],
            lr: 1e-3,
            batch_size: 512,
            steps: 100_000,
            seed: 0,
        }
    }
}

/// An actor being trained by behaviour cloning.
pub struct BcLearner {
    pub net: Mlp,
    optimizer: Adam,
    noise: Noise,
    observations: Tensor,
    actions: Tensor,
    rows: usize,
    batch_size: usize,
    device: Device,
}

impl BcLearner {
    /// A learner on the CPU.
    pub fn new(
        settings: &BcSettings,
        observations: &[f32],
        actions: &[f32],
        obs_dim: usize,
        act_dim: usize,
    ) -> anyhow::Result<Self> {
        Self::on_device(settings, observations, actions, obs_dim, act_dim, &Device::Cpu)
    }

    /// A learner whose network, data and batches live on `device` (the dataset is uploaded once; each step draws
    /// its batch indices from the seed on the CPU and gathers the rows on the device). The first weights are the
    /// CPU's, so a run differs between devices only by float rounding.
    pub fn on_device(
        settings: &BcSettings,
        observations: &[f32],
        actions: &[f32],
        obs_dim: usize,
        act_dim: usize,
        device: &Device,
    ) -> anyhow::Result<Self> {
        let rows = observations.len() / obs_dim;
        anyhow::ensure!(rows > 0, "no transitions to learn from");
        anyhow::ensure!(
            actions.len() == rows * act_dim,
            "observations and actions disagree in length"
        );
        let mut noise = Noise::seeded(settings.seed);
        let sizes = dsrl_policy::mlp::layer_sizes(obs_dim, &settings.hidden_sizes, act_dim);
        let net =
            Mlp::orthogonal("actor.net", &sizes, Activation::Relu, 2f64.sqrt(), 1.0, &mut noise)?.to_device(device)?;
        let optimizer = Adam::new(net.named_vars(), settings.lr, None)?;
        Ok(BcLearner {
            net,
            optimizer,
            noise,
            observations: matrix(observations, rows, obs_dim)?.to_device(device)?,
            actions: matrix(actions, rows, act_dim)?.to_device(device)?,
            rows,
            batch_size: settings.batch_size,
            device: device.clone(),
        })
    }

    /// `max_action · tanh(net(obs))`.
    pub fn act(&self, obs: &Tensor) -> anyhow::Result<Tensor> {
        Ok(self.net.forward(obs)?.tanh()?.affine(MAX_ACTION, 0.0)?)
    }

    /// One Adam step on a uniformly drawn batch; returns its MSE.
    pub fn step(&mut self) -> anyhow::Result<f64> {
        let idx: Vec<u32> = (0..self.batch_size)
            .map(|_| (self.noise.next_u64() % self.rows as u64) as u32)
            .collect();
        let idx = Tensor::from_slice(&idx, idx.len(), &self.device)?;
        let (loss, grads) = self.net.tanh_mse_gradients(
            &self.observations.index_select(&idx, 0)?,
            &self.actions.index_select(&idx, 0)?,
            MAX_ACTION,
        )?;
        self.optimizer.step(&grads)?;
        Ok(f64::from(loss))
    }

    /// Writes the actor as an `mlp_actor` policy.
    pub fn write(
        &self,
        dir: &Path,
        task: &str,
        hidden_sizes: &[usize],
        conditioning: Conditioning,
        training: serde_json::Value,
    ) -> anyhow::Result<()> {
        let config = PolicyConfig {
            format: checkpoint::FORMAT.into(),
            task: task.to_owned(),
            obs_dim: self.net.input_dim(),
            act_dim: self.net.output_dim(),
            architecture: Architecture::MlpActor {
                hidden_sizes: hidden_sizes.to_vec(),
                activation: Activation::Relu,
                max_action: MAX_ACTION,
            },
            observation_normalization: None,
            conditioning,
            training: Some(training),
        };
        // Written as float32 on the CPU whichever device trained it: the checkpoint format has no device.
        let tensors = dsrl_policy::tensors_of(self.net.named_vars())
            .into_iter()
            .map(|(name, t)| Ok((name, t.to_device(&Device::Cpu)?)))
            .collect::<candle_core::Result<Vec<_>>>()?;
        checkpoint::write(dir, &config, &tensors)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn devices_are_named_and_cuda_without_the_feature_says_how_to_get_it() {
        assert!(training_device("cpu").unwrap().is_cpu());
        assert_eq!(device_name(&Device::Cpu), "cpu");
        for bad in ["gpu", "cuda:x", "cuda:-1", ""] {
            let err = training_device(bad).unwrap_err().to_string();
            assert!(err.contains("the devices are cpu, cuda and cuda:N"), "{bad}: {err}");
        }
        if !cfg!(feature = "cuda") {
            let err = training_device("cuda:1").unwrap_err().to_string();
            assert!(
                err.contains("built without the `cuda` feature") && err.contains("build-cuda.sh"),
                "{err}"
            );
        }
    }

    #[test]
    fn bc_learns_a_linear_expert_and_bc_safe_keeps_only_safe_episodes() {
        // 40 one-dimensional episodes of 10 steps; the expert's action is 0.5·obs; episode e costs e.
        let mut noise = Noise::seeded(1);
        let mut d = Demonstrations::empty(1, 1);
        for e in 0..40 {
            for _ in 0..10 {
                let o = (noise.uniform() * 2.0 - 1.0) as f32;
                d.observations.push(o);
                d.actions.push(0.5 * o);
            }
            d.episodes.push((e * 10, 10, 0.0, e as f64));
        }
        let (obs, act, kept) = d.select(Some(9.5));
        assert_eq!((kept, obs.len(), act.len()), (10, 100, 100));
        assert_eq!(obs[..], d.observations[..100]);
        assert_eq!(d.select(None).2, 40);

        let settings = BcSettings {
            hidden_sizes: vec![32, 32],
            batch_size: 64,
            steps: 600,
            ..BcSettings::default()
        };
        let (obs, act, _) = d.select(None);
        let mut learner = BcLearner::new(&settings, &obs, &act, 1, 1).unwrap();
        let first = learner.step().unwrap();
        let mut last = first;
        for _ in 1..settings.steps {
            last = learner.step().unwrap();
        }
        assert!(last < first / 20.0 && last < 2e-3, "MSE {first} -> {last}");
        let probe = matrix(&[-0.8, 0.0, 0.6], 3, 1).unwrap();
        let got = learner
            .act(&probe)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        for (g, want) in got.iter().zip([-0.4f32, 0.0, 0.3]) {
            assert!((g - want).abs() < 0.05, "{got:?}");
        }

        // The written policy acts exactly like the learner.
        let dir = tempfile::tempdir().unwrap();
        learner
            .write(
                dir.path(),
                "OfflineBallRun-v0",
                &[32, 32],
                Conditioning::Unconditioned,
                serde_json::json!({}),
            )
            .unwrap();
        let (config, tensors) = checkpoint::read(dir.path()).unwrap();
        let policy = dsrl_policy::Policy::load(&config, &tensors).unwrap();
        assert_eq!(policy.act(&probe).unwrap(), got);
    }
}
