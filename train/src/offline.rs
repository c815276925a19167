//! What the per-threshold offline learners (BCQ-L, BEAR-L, CPQ, COptiDICE) share on the training side: the
//! transitions as tensors with OSRL's uniform batch sampler, the learner interface the CLI drives, and the writer of
//! the squashed Gaussian actor's checkpoint.

use std::path::Path;

use dsrl_policy::adam::Adam;
use dsrl_policy::checkpoint::{self, Architecture, Conditioning, PolicyConfig};
use dsrl_policy::mlp::Activation;
use dsrl_policy::noise::Noise;
use dsrl_policy::squashed::SquashedGaussianActor;
use dsrl_policy::{Device, Tensor, Var};

use crate::{Demonstrations, MAX_ACTION};

/// Named figures of one training step (losses, multipliers), for the progress line and the record.
pub type Figures = Vec<(&'static str, f64)>;

/// One learner trained for one cost threshold, stepped by the CLI.
pub trait ThresholdLearner {
    /// One gradient step on a freshly drawn batch; named figures for the progress line and the record.
    fn step(&mut self) -> anyhow::Result<Figures> {
        let batch = self.sample()?;
        self.update(&batch)
    }
    /// A batch drawn as OSRL's `TransitionDataset` draws one (uniform, with replacement), scaled.
    fn sample(&mut self) -> anyhow::Result<Batch>;
    /// One gradient step on `batch`: every network's update, in OSRL's order.
    fn update(&mut self, batch: &Batch) -> anyhow::Result<Figures>;
    /// The networks under OSRL's attribute names (`actor`, `actor_old`, `critic`, ...), each with its variables
    /// in the order of OSRL's `parameters()`, for tests/parity (which loads OSRL's initial weights into them).
    fn modules(&self) -> Vec<(&'static str, Vec<(String, Var)>)>;
    /// The optimizers under OSRL's attribute names (`actor_optim`, ...), for tests/parity.
    fn optimizers(&mut self) -> Vec<(&'static str, &mut Adam)>;
    /// The learner's random numbers (batches, latents, action samples), for tests/parity to seed.
    fn noise(&mut self) -> &mut Noise;
    /// The per-step cost-Q threshold the learner holds its policy to.
    fn qc_threshold(&self) -> f64;
    /// Transitions per batch.
    fn batch_size(&self) -> usize;
    /// The hyperparameters, as recorded in `policy.json`.
    fn settings(&self) -> String;
    /// Writes the evaluator's checkpoint for threshold `kappa` with `training` recorded.
    fn write(&self, dir: &Path, task: &str, kappa: f64, training: serde_json::Value) -> anyhow::Result<()>;
}

/// `mean(|τ − 1[u < 0]|·u²)`, IQL's expectile loss (CAPS, FISOR, LSPC): `τ > ½` an upper expectile of what
/// `u` measures the value against, `τ < ½` a lower one.
pub fn expectile_loss(u: &Tensor, tau: f64) -> anyhow::Result<Tensor> {
    let below = u.lt(0.0)?.to_dtype(dsrl_policy::DType::F32)?;
    let weight = below.affine(-1.0, tau)?.abs()?;
    Ok(weight.mul(&u.sqr()?)?.mean_all()?)
}

/// A learner trained once whose model is scored at every threshold (CAPS, FISOR, LSPC), stepped by the CLI.
pub trait EveryThresholdLearner {
    /// One training step on a freshly drawn batch; named figures for the progress line and the record.
    fn step(&mut self) -> anyhow::Result<Figures>;
    /// Writes the evaluator's checkpoint with `training` recorded.
    fn write(&self, dir: &Path, task: &str, training: serde_json::Value) -> anyhow::Result<()>;
}

/// The dataset's transitions as tensors (OSRL's `TransitionDataset`), sampled uniformly with replacement.
pub struct Transitions {
    obs: Tensor,
    next_obs: Tensor,
    act: Tensor,
    reward: Tensor,
    cost: Tensor,
    done: Tensor,
    is_init: Tensor,
    rows: usize,
    /// The fraction of rows that start an episode (COptiDICE's `init_state_propotion`).
    pub init_proportion: f64,
}

/// A sampled batch; rewards and costs already multiplied by the scales.
pub struct Batch {
    pub obs: Tensor,
    pub next_obs: Tensor,
    pub act: Tensor,
    pub reward: Tensor,
    pub cost: Tensor,
    pub done: Tensor,
    /// 1 for an episode's first transition (`is_init[0] = 1`, `is_init[t] = done[t − 1]`).
    pub is_init: Tensor,
}

impl Transitions {
    /// The transitions as tensors on `device` (the one the learner trains on).
    pub fn new(data: &Demonstrations, device: &Device) -> anyhow::Result<Transitions> {
        let (o, a, rows) = (data.obs_dim, data.act_dim, data.rows());
        anyhow::ensure!(rows > 0, "no transitions to learn from");
        let m = |v: &[f32], cols: usize| Tensor::from_vec(v.to_vec(), (rows, cols), device);
        let column = |v: &[f32]| Tensor::from_vec(v.to_vec(), rows, device);
        let is_init: Vec<f32> = std::iter::once(1.0)
            .chain(data.dones[..rows - 1].iter().copied())
            .collect();
        let init_proportion = is_init.iter().map(|&v| f64::from(v)).sum::<f64>() / rows as f64;
        Ok(Transitions {
            obs: m(&data.observations, o)?,
            next_obs: m(&data.next_observations, o)?,
            act: m(&data.actions, a)?,
            reward: column(&data.rewards)?,
            cost: column(&data.costs)?,
            done: column(&data.dones)?,
            is_init: column(&is_init)?,
            rows,
            init_proportion,
        })
    }

    /// The device the transitions (and so the learner) live on.
    pub fn device(&self) -> &Device {
        self.obs.device()
    }

    /// `size` rows drawn uniformly with replacement from `noise`.
    pub fn sample(&self, size: usize, reward_scale: f64, cost_scale: f64, noise: &mut Noise) -> anyhow::Result<Batch> {
        let idx: Vec<u32> = (0..size)
            .map(|_| (noise.next_u64() % self.rows as u64) as u32)
            .collect();
        let idx = Tensor::from_vec(idx, size, self.device())?;
        let pick = |t: &Tensor| t.index_select(&idx, 0);
        Ok(Batch {
            obs: pick(&self.obs)?,
            next_obs: pick(&self.next_obs)?,
            act: pick(&self.act)?,
            reward: pick(&self.reward)?.affine(reward_scale, 0.0)?,
            cost: pick(&self.cost)?.affine(cost_scale, 0.0)?,
            done: pick(&self.done)?,
            is_init: pick(&self.is_init)?,
        })
    }

    /// The per-dimension standard deviations (population, as NumPy's `std`) of observations and actions, `[1, dim]`
    /// each (COptiDICE's input noise scale).
    pub fn stds(&self) -> anyhow::Result<(Tensor, Tensor)> {
        let std = |t: &Tensor| -> anyhow::Result<Tensor> {
            let mean = t.mean_keepdim(0)?;
            Ok(t.broadcast_sub(&mean)?.sqr()?.mean_keepdim(0)?.sqrt()?)
        };
        Ok((std(&self.obs)?, std(&self.act)?))
    }
}

/// `[rows, cols]` standard normal draws from `noise` (drawn on the host, so a run's numbers do not depend on the
/// device), on `device`.
pub fn normals(noise: &mut Noise, rows: usize, cols: usize, device: &Device) -> anyhow::Result<Tensor> {
    Ok(Tensor::from_vec(noise.normals_f32(rows * cols), (rows, cols), device)?)
}

/// Writes a trained squashed Gaussian actor as the evaluator's `squashed_gaussian_mlp` for threshold `kappa` (it
/// plays `max_action · tanh(μ)`, OSRL's deterministic evaluation).
pub fn write_squashed_actor(
    actor: &SquashedGaussianActor,
    hidden_sizes: &[usize],
    dir: &Path,
    task: &str,
    obs_dim: usize,
    kappa: f64,
    training: serde_json::Value,
) -> anyhow::Result<()> {
    let config = PolicyConfig {
        format: checkpoint::FORMAT.into(),
        task: task.to_owned(),
        obs_dim,
        act_dim: actor.act_dim,
        architecture: Architecture::SquashedGaussianMlp {
            hidden_sizes: hidden_sizes.to_vec(),
            activation: Activation::Relu,
            max_action: MAX_ACTION,
        },
        observation_normalization: None,
        conditioning: Conditioning::PerThreshold { cost_threshold: kappa },
        training: Some(training),
    };
    checkpoint::write(dir, &config, &dsrl_policy::tensors_of(actor.named_vars()))?;
    Ok(())
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// 30 two-dimensional episodes of 10 steps: the behaviour action is 0.5·obs, reward 1 − |a − 0.5·o|, and every
    /// step costs 1 in the second half of the episodes.
    pub(crate) fn toy() -> Demonstrations {
        let mut noise = Noise::seeded(5);
        let mut d = Demonstrations::empty(2, 1);
        for e in 0..30 {
            let mut o = [noise.uniform() as f32, noise.uniform() as f32];
            for t in 0..10 {
                let a = 0.5 * o[0];
                let next = [(o[0] + 0.1).min(1.0), o[1]];
                d.observations.extend_from_slice(&o);
                d.next_observations.extend_from_slice(&next);
                d.actions.push(a);
                d.rewards.push(1.0);
                d.costs.push(if e >= 15 { 1.0 } else { 0.0 });
                d.dones.push(if t == 9 { 1.0 } else { 0.0 });
                o = next;
            }
            d.episodes.push((e * 10, 10, 10.0, if e >= 15 { 10.0 } else { 0.0 }));
        }
        d
    }

    /// Steps `learner` `n` times and returns the first and last figures.
    pub(crate) fn run(learner: &mut dyn ThresholdLearner, n: usize) -> (Figures, Figures) {
        run_steps(|| learner.step(), n)
    }

    /// Calls `step` `n` times and returns the first and last figures, every one of them finite.
    pub(crate) fn run_steps(mut step: impl FnMut() -> anyhow::Result<Figures>, n: usize) -> (Figures, Figures) {
        let first = step().unwrap();
        let mut last = first.clone();
        for _ in 1..n {
            last = step().unwrap();
        }
        for (name, v) in first.iter().chain(&last) {
            assert!(v.is_finite(), "{name} = {v}");
        }
        (first, last)
    }

    /// The values of the first variable of `vars` (a network's first weight matrix): what determinism tests compare.
    pub(crate) fn first_weights(vars: Vec<(String, dsrl_policy::Var)>) -> Vec<f32> {
        vars[0].1.as_tensor().flatten_all().unwrap().to_vec1().unwrap()
    }

    /// Asserts that each of `names` is lower in `last` than in `first`.
    pub(crate) fn assert_falls(first: &Figures, last: &Figures, names: &[&str]) {
        for name in names {
            assert!(
                figure(last, name) < figure(first, name),
                "{name}: {first:?} -> {last:?}"
            );
        }
    }

    pub(crate) fn figure(figures: &[(&'static str, f64)], name: &str) -> f64 {
        figures
            .iter()
            .find(|(n, _)| *n == name)
            .unwrap_or_else(|| panic!("no {name} in {figures:?}"))
            .1
    }

    /// Writes the checkpoint of a learner trained once and reads it back as the evaluator does: its `policy.json`,
    /// its tensors and the loaded policy.
    pub(crate) fn read_back(
        learner: &dyn EveryThresholdLearner,
        steps: u64,
    ) -> (
        PolicyConfig,
        std::collections::HashMap<String, Tensor>,
        dsrl_policy::Policy,
    ) {
        let dir = tempfile::tempdir().unwrap();
        learner
            .write(dir.path(), "toy", serde_json::json!({ "steps": steps }))
            .unwrap();
        let (config, tensors) = checkpoint::read(dir.path()).unwrap();
        let policy = dsrl_policy::Policy::load(&config, &tensors).unwrap();
        (config, tensors, policy)
    }

    /// Writes `learner`, reads it back as the evaluator does and checks it plays `expected` at `obs` (one row of 2).
    pub(crate) fn plays_as_written(learner: &dyn ThresholdLearner, obs: [f32; 2], expected: f32) {
        let dir = tempfile::tempdir().unwrap();
        learner
            .write(dir.path(), "toy", 10.0, serde_json::json!({"steps": 1}))
            .unwrap();
        let (config, tensors) = checkpoint::read(dir.path()).unwrap();
        assert!(matches!(config.conditioning, Conditioning::PerThreshold { cost_threshold } if cost_threshold == 10.0));
        let policy = dsrl_policy::Policy::load(&config, &tensors).unwrap();
        let mut rollout = policy.rollout(10.0, 1).unwrap();
        rollout.start_episode(0, 42).unwrap();
        let played = rollout.act(&[0], &obs).unwrap();
        assert!((played[0] - expected).abs() < 1e-5, "{played:?} vs {expected}");
    }

    #[test]
    fn batches_mark_episode_starts_and_the_standard_deviations_are_numpys() {
        let data = toy();
        let t = Transitions::new(&data, &Device::Cpu).unwrap();
        // 30 episodes in 300 rows.
        assert!((t.init_proportion - 0.1).abs() < 1e-12);
        let starts: Vec<f32> = t.is_init.to_vec1().unwrap();
        assert_eq!(starts[0], 1.0);
        assert_eq!(starts[10], 1.0);
        assert_eq!(starts[11], 0.0);
        let mut noise = Noise::seeded(1);
        let b = t.sample(64, 0.1, 2.0, &mut noise).unwrap();
        let rewards: Vec<f32> = b.reward.to_vec1().unwrap();
        assert!(rewards.iter().all(|&r| (r - 0.1).abs() < 1e-7));
        let costs: Vec<f32> = b.cost.to_vec1().unwrap();
        assert!(costs.iter().all(|&c| c == 0.0 || c == 2.0));
        let (obs_std, act_std) = t.stds().unwrap();
        let a = &data.actions;
        let mean = a.iter().map(|&v| f64::from(v)).sum::<f64>() / a.len() as f64;
        let var = a.iter().map(|&v| (f64::from(v) - mean).powi(2)).sum::<f64>() / a.len() as f64;
        let got: Vec<Vec<f32>> = act_std.to_vec2().unwrap();
        assert!((f64::from(got[0][0]) - var.sqrt()).abs() < 1e-5);
        assert_eq!(obs_std.dims(), &[1, 2]);
    }
}
