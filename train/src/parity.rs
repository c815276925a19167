//! One update of a per-threshold learner from given weights, batch and random numbers, with everything it computed
//! written out: what tests/parity/osrl_step_check.py holds to OSRL's own PyTorch code (`dsrl-train parity`,
//! hidden). The script writes `<dir>/parity.json` (algorithm, sizes, threshold, the noise seed), `init.safetensors`
//! (OSRL's initial weights as `<module>/<i>`, `<module>` an OSRL attribute name and `i` the position in its
//! `parameters()`) and `batch.safetensors`; this writes `candle.safetensors`: `loss/<figure>`, `grad/<optimizer>/<i>`
//! (the gradient each optimizer stepped with) and `param/<module>/<i>` (every weight after the update).

use std::collections::HashMap;
use std::path::Path;

use anyhow::Context;
use dsrl_policy::noise::Noise;
use dsrl_policy::{Device, Tensor};
use serde::Deserialize;

use crate::Demonstrations;
use crate::bcql::{BcqlLearner, BcqlSettings};
use crate::bearl::{BearlLearner, BearlSettings};
use crate::cdt::{CdtLearner, CdtSettings, Windows};
use crate::coptidice::{CoptidiceLearner, CoptidiceSettings};
use crate::cpq::{CpqLearner, CpqSettings};
use crate::offline::{Batch, ThresholdLearner};

#[derive(Debug, Deserialize)]
struct Spec {
    algorithm: String,
    obs_dim: usize,
    act_dim: usize,
    #[serde(default)]
    hidden_sizes: Vec<usize>,
    #[serde(default)]
    vae_hidden: usize,
    #[serde(default)]
    cost_threshold: f64,
    episode_len: usize,
    noise_seed: u64,
    /// CDT's sizes: embedding, layers, heads, window.
    #[serde(default)]
    cdt: Option<(usize, usize, usize, usize)>,
}

pub fn run(dir: &Path) -> anyhow::Result<()> {
    let spec: Spec = serde_json::from_slice(&std::fs::read(dir.join("parity.json")).context("reading parity.json")?)?;
    if spec.algorithm == "cdt" {
        return run_cdt(dir, &spec);
    }
    let batch = candle_core::safetensors::load(dir.join("batch.safetensors"), &Device::Cpu)?;
    let column = |name: &str| -> anyhow::Result<Tensor> {
        batch
            .get(name)
            .cloned()
            .with_context(|| format!("batch.safetensors has no {name}"))
    };
    let batch = Batch {
        obs: column("observations")?,
        next_obs: column("next_observations")?,
        act: column("actions")?,
        reward: column("rewards")?,
        cost: column("costs")?,
        done: column("done")?,
        is_init: column("is_init")?,
    };
    let size = batch.obs.dim(0)?;
    let data = demonstrations_of(&batch, spec.obs_dim, spec.act_dim)?;
    let mut learner = learner(&spec, &data, size)?;

    let init = candle_core::safetensors::load(dir.join("init.safetensors"), &Device::Cpu)?;
    let mut loaded = 0;
    for (module, vars) in learner.modules() {
        for (i, (name, var)) in vars.iter().enumerate() {
            let key = format!("{module}/{i}");
            let value = init
                .get(&key)
                .with_context(|| format!("init.safetensors has no {key} ({name})"))?;
            anyhow::ensure!(
                value.dims() == var.dims(),
                "{key} ({name}): OSRL's shape {:?}, ours {:?}",
                value.dims(),
                var.dims()
            );
            var.set(value)?;
            loaded += 1;
        }
    }
    anyhow::ensure!(
        loaded == init.len(),
        "init.safetensors has {} tensors, the learner {loaded}",
        init.len()
    );
    *learner.noise() = Noise::seeded(spec.noise_seed);
    for (_, optimizer) in learner.optimizers() {
        optimizer.keep_gradients = true;
    }

    let figures = learner.update(&batch)?;

    let mut out: HashMap<String, Tensor> = HashMap::new();
    for (name, value) in figures {
        out.insert(format!("loss/{name}"), Tensor::new(&[value], &Device::Cpu)?);
    }
    for (optimizer_name, optimizer) in learner.optimizers() {
        for (i, gradient) in optimizer.last_gradients() {
            out.insert(format!("grad/{optimizer_name}/{i}"), gradient.clone());
        }
    }
    for (module, vars) in learner.modules() {
        for (i, (_, var)) in vars.iter().enumerate() {
            out.insert(format!("param/{module}/{i}"), var.as_tensor().clone());
        }
    }
    candle_core::safetensors::save(&out, dir.join("candle.safetensors"))?;
    Ok(())
}

/// The learner of `spec.algorithm` with OSRL's settings but the given sizes.
fn learner(spec: &Spec, data: &Demonstrations, batch_size: usize) -> anyhow::Result<Box<dyn ThresholdLearner>> {
    let hidden_sizes = spec.hidden_sizes.clone();
    let (kappa, len) = (spec.cost_threshold, spec.episode_len);
    Ok(match spec.algorithm.as_str() {
        "bcql" => Box::new(BcqlLearner::new(
            BcqlSettings {
                hidden_sizes,
                vae_hidden: spec.vae_hidden,
                batch_size,
                ..BcqlSettings::default()
            },
            data,
            kappa,
            len,
        )?),
        "bearl" => Box::new(BearlLearner::new(
            BearlSettings {
                hidden_sizes,
                vae_hidden: spec.vae_hidden,
                batch_size,
                ..BearlSettings::default()
            },
            data,
            kappa,
            len,
        )?),
        "cpq" => Box::new(CpqLearner::new(
            CpqSettings {
                hidden_sizes,
                vae_hidden: spec.vae_hidden,
                batch_size,
                ..CpqSettings::default()
            },
            data,
            kappa,
            len,
        )?),
        "coptidice" => Box::new(CoptidiceLearner::new(
            CoptidiceSettings {
                hidden_sizes,
                batch_size,
                ..CoptidiceSettings::default()
            },
            data,
            kappa,
            len,
        )?),
        other => anyhow::bail!("no parity run for {other:?}: bcql, bearl, cpq or coptidice"),
    })
}

/// The batch's rows as the learner's data (what its statistics, such as COptiDICE's standard deviations and initial
/// proportion, are computed from).
fn demonstrations_of(batch: &Batch, obs_dim: usize, act_dim: usize) -> anyhow::Result<Demonstrations> {
    let flat = |t: &Tensor| -> anyhow::Result<Vec<f32>> { Ok(t.flatten_all()?.to_vec1::<f32>()?) };
    let mut data = Demonstrations::empty(obs_dim, act_dim);
    data.observations = flat(&batch.obs)?;
    data.next_observations = flat(&batch.next_obs)?;
    data.actions = flat(&batch.act)?;
    data.rewards = flat(&batch.reward)?;
    data.costs = flat(&batch.cost)?;
    data.dones = flat(&batch.done)?;
    Ok(data)
}

/// CDT (no dropout, so the step is deterministic): weights by OSRL's parameter names (`cdt.<name>` as in its
/// exports, and `log_temperature`); the windows from `batch.safetensors`; gradients and weights written by name.
fn run_cdt(dir: &Path, spec: &Spec) -> anyhow::Result<()> {
    let (embedding_dim, num_layers, num_heads, seq_len) = spec.cdt.context("parity.json has no cdt sizes")?;
    let batch = candle_core::safetensors::load(dir.join("batch.safetensors"), &Device::Cpu)?;
    let get = |name: &str| -> anyhow::Result<Tensor> {
        batch
            .get(name)
            .cloned()
            .with_context(|| format!("batch.safetensors has no {name}"))
    };
    let windows = Windows {
        states: get("states")?,
        actions: get("actions")?,
        returns_to_go: get("returns")?,
        costs_to_go: get("costs_return")?,
        timesteps: get("time_steps")?.to_dtype(candle_core::DType::U32)?,
        mask: get("mask")?,
        cost_labels: get("costs")?,
    };
    // One episode as the learner's data: `new` needs trajectories; the windows come from the file.
    let mut data = Demonstrations::empty(spec.obs_dim, spec.act_dim);
    data.observations = vec![0.0; spec.obs_dim];
    data.next_observations = vec![0.0; spec.obs_dim];
    data.actions = vec![0.0; spec.act_dim];
    data.rewards = vec![0.0];
    data.costs = vec![0.0];
    data.dones = vec![1.0];
    data.episodes = vec![(0, 1, 0.0, 0.0)];
    let settings = CdtSettings {
        embedding_dim,
        num_layers,
        num_heads,
        seq_len,
        dropout: 0.0,
        batch_size: windows.states.dim(0)?,
        ..CdtSettings::default()
    };
    let mut learner = CdtLearner::new(settings, data, spec.episode_len, None)?;
    let init = candle_core::safetensors::load(dir.join("init.safetensors"), &Device::Cpu)?;
    let mut vars = learner.model.named_vars();
    vars.push(("log_temperature".into(), learner.log_temperature().clone()));
    for (name, var) in &vars {
        let value = init
            .get(name)
            .with_context(|| format!("init.safetensors has no {name}"))?;
        anyhow::ensure!(
            value.dims() == var.dims(),
            "{name}: OSRL's shape {:?}, ours {:?}",
            value.dims(),
            var.dims()
        );
        var.set(value)?;
    }
    let unused: Vec<&String> = init.keys().filter(|k| !vars.iter().any(|(n, _)| n == *k)).collect();
    anyhow::ensure!(
        unused.is_empty(),
        "init.safetensors has tensors the model lacks: {unused:?}"
    );
    *learner.noise() = Noise::seeded(spec.noise_seed);
    let model_names: Vec<String> = learner.model.named_vars().into_iter().map(|(n, _)| n).collect();
    for (_, optimizer) in learner.optimizers() {
        optimizer.keep_gradients = true;
    }

    let figures = learner.update(&windows)?;

    let mut out: HashMap<String, Tensor> = HashMap::new();
    for (name, value) in figures {
        out.insert(format!("loss/{name}"), Tensor::new(&[value], &Device::Cpu)?);
    }
    for (optimizer_name, optimizer) in learner.optimizers() {
        for (i, gradient) in optimizer.last_gradients() {
            let name = if optimizer_name == "optim" {
                model_names[*i].clone()
            } else {
                "log_temperature".to_owned()
            };
            out.insert(format!("grad/{optimizer_name}/{name}"), gradient.clone());
        }
    }
    for (name, var) in &vars {
        out.insert(format!("param/{name}"), var.as_tensor().clone());
    }
    candle_core::safetensors::save(&out, dir.join("candle.safetensors"))?;
    Ok(())
}
