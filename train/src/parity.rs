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
use dsrl_policy::{Device, Tensor, Var};
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
    let file = Tensors::load(dir, "batch.safetensors")?;
    let batch = Batch {
        obs: file.get("observations")?,
        next_obs: file.get("next_observations")?,
        act: file.get("actions")?,
        reward: file.get("rewards")?,
        cost: file.get("costs")?,
        done: file.get("done")?,
        is_init: file.get("is_init")?,
    };
    let size = batch.obs.dim(0)?;
    let data = demonstrations_of(&batch, spec.obs_dim, spec.act_dim)?;
    let mut learner = learner(&spec, &data, size)?;
    let vars: Vec<(String, Var)> = learner
        .modules()
        .into_iter()
        .flat_map(|(module, vars)| {
            vars.into_iter()
                .enumerate()
                .map(move |(i, (_, var))| (format!("{module}/{i}"), var))
        })
        .collect();
    load_weights(dir, &vars)?;
    *learner.noise() = Noise::seeded(spec.noise_seed);
    for (_, optimizer) in learner.optimizers() {
        optimizer.keep_gradients = true;
    }

    let figures = learner.update(&batch)?;

    let mut gradients = Vec::new();
    for (optimizer_name, optimizer) in learner.optimizers() {
        for (i, gradient) in optimizer.last_gradients() {
            gradients.push((format!("{optimizer_name}/{i}"), gradient.clone()));
        }
    }
    write_step(dir, figures, gradients, &vars)
}

/// A safetensors file of the script's, read by name.
struct Tensors {
    file: &'static str,
    tensors: HashMap<String, Tensor>,
}

impl Tensors {
    fn load(dir: &Path, file: &'static str) -> anyhow::Result<Tensors> {
        let tensors = candle_core::safetensors::load(dir.join(file), &Device::Cpu)?;
        Ok(Tensors { file, tensors })
    }

    fn get(&self, name: &str) -> anyhow::Result<Tensor> {
        self.tensors
            .get(name)
            .cloned()
            .with_context(|| format!("{} has no {name}", self.file))
    }
}

/// Sets each variable from `init.safetensors` under its key, shapes checked; a tensor no variable takes is an
/// error too (the two sides would be comparing different networks).
fn load_weights(dir: &Path, vars: &[(String, Var)]) -> anyhow::Result<()> {
    let init = Tensors::load(dir, "init.safetensors")?;
    for (key, var) in vars {
        let value = init.get(key)?;
        anyhow::ensure!(
            value.dims() == var.dims(),
            "{key}: OSRL's shape {:?}, ours {:?}",
            value.dims(),
            var.dims()
        );
        var.set(&value)?;
    }
    let unused: Vec<&String> = init
        .tensors
        .keys()
        .filter(|k| !vars.iter().any(|(key, _)| key == *k))
        .collect();
    anyhow::ensure!(
        unused.is_empty(),
        "init.safetensors has tensors the learner lacks: {unused:?}"
    );
    Ok(())
}

/// Writes `candle.safetensors`: `loss/<figure>`, `grad/<key>` and `param/<key>` (every weight after the step).
fn write_step(
    dir: &Path,
    figures: crate::offline::Figures,
    gradients: Vec<(String, Tensor)>,
    vars: &[(String, Var)],
) -> anyhow::Result<()> {
    let mut out: HashMap<String, Tensor> = HashMap::new();
    for (name, value) in figures {
        out.insert(format!("loss/{name}"), Tensor::new(&[value], &Device::Cpu)?);
    }
    for (key, gradient) in gradients {
        out.insert(format!("grad/{key}"), gradient);
    }
    for (key, var) in vars {
        out.insert(format!("param/{key}"), var.as_tensor().clone());
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
    let file = Tensors::load(dir, "batch.safetensors")?;
    let windows = Windows {
        states: file.get("states")?,
        actions: file.get("actions")?,
        returns_to_go: file.get("returns")?,
        costs_to_go: file.get("costs_return")?,
        timesteps: file.get("time_steps")?.to_dtype(candle_core::DType::U32)?,
        mask: file.get("mask")?,
        cost_labels: file.get("costs")?,
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
    let mut vars = learner.model.named_vars();
    vars.push(("log_temperature".into(), learner.log_temperature().clone()));
    load_weights(dir, &vars)?;
    *learner.noise() = Noise::seeded(spec.noise_seed);
    let model_names: Vec<String> = learner.model.named_vars().into_iter().map(|(n, _)| n).collect();
    for (_, optimizer) in learner.optimizers() {
        optimizer.keep_gradients = true;
    }

    let figures = learner.update(&windows)?;

    let mut gradients = Vec::new();
    for (optimizer_name, optimizer) in learner.optimizers() {
        for (i, gradient) in optimizer.last_gradients() {
            let name = if optimizer_name == "optim" {
                model_names[*i].clone()
            } else {
                "log_temperature".to_owned()
            };
            gradients.push((format!("{optimizer_name}/{name}"), gradient.clone()));
        }
    }
    write_step(dir, figures, gradients, &vars)
}
