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
use crate::coptidice::{CoptidiceLearner, CoptidiceSettings};
use crate::cpq::{CpqLearner, CpqSettings};
use crate::offline::{Batch, ThresholdLearner};

#[derive(Debug, Deserialize)]
struct Spec {
    algorithm: String,
    obs_dim: usize,
    act_dim: usize,
    hidden_sizes: Vec<usize>,
    vae_hidden: usize,
    cost_threshold: f64,
    episode_len: usize,
    noise_seed: u64,
}

pub fn run(dir: &Path) -> anyhow::Result<()> {
    let spec: Spec = serde_json::from_slice(&std::fs::read(dir.join("parity.json")).context("reading parity.json")?)?;
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
