//! CDT (OSRL `cdt.py`, spec 5.4): the Constrained Decision Transformer, trained once and conditioned at evaluation
//! on (reward, cost) return targets, one pair per benchmark threshold (`data/cdt_targets.csv`, OSRL's configs).
//!
//! Training, as OSRL's: windows of K = 10 timesteps from trajectories drawn with probability ∝ max(0, 70 − C)
//! (C the trajectory's cost return; OSRL's linear cost sampling), each starting at a uniform step and zero-padded
//! at the end; the model (embedding 128, 3 pre-LN blocks of 8 heads, dropout 0.1) predicts a diagonal Gaussian
//! action at each state token and a cost class at each action token:
//! `loss = −(mean log N(a | μ, σ) + τ·mean entropy) + 0.02·NLL(cost)`, means over the valid (unpadded) positions;
//! AdamW (lr 1e-4, weight decay 1e-4, gradient norm clipped to 0.25) with a linear warm-up over 500 steps; the
//! entropy temperature τ (from 0.1) follows `log τ ← Adam(τ·(H − (−act_dim)))`, lr 1e-4.
//!
//! The data: every trajectory plus OSRL's return augmentation (`cdt_augment`: 20% more, relabelled towards the
//! Pareto frontier). Departures from OSRL, recorded with every trained model: the augmentation's draws come from
//! the seeded generator (not Python's and NumPy's), and the state-prediction head (weight 0 in OSRL's loss) is not
//! decayed.

use std::path::Path;

use dsrl_policy::adam::Adam;
use dsrl_policy::cdt::{Cdt, CdtShape, Training};
use dsrl_policy::checkpoint::{self, Architecture, Conditioning, PolicyConfig, ReturnTarget};
use dsrl_policy::layers::log_softmax;
use dsrl_policy::noise::Noise;
use dsrl_policy::{Device, Tensor, Var};

use crate::cdt_augment::{Augmentation, augment};
use crate::offline::Figures;
use crate::{Demonstrations, MAX_ACTION};

/// OSRL's CDT configuration (spec 5.4, `examples/configs/cdt_configs.py`'s base).
#[derive(Debug, Clone, PartialEq)]
pub struct CdtSettings {
    pub embedding_dim: usize,
    pub num_layers: usize,
    pub num_heads: usize,
    pub seq_len: usize,
    pub dropout: f64,
    pub batch_size: usize,
    pub lr: f64,
    pub weight_decay: f64,
    pub clip_grad: f64,
    pub warmup_steps: u64,
    pub reward_scale: f64,
    pub cost_scale: f64,
    pub loss_cost_weight: f64,
    pub init_temperature: f64,
    /// Trajectories are drawn with probability ∝ max(0, cost_sample_cap − cost return).
    pub cost_sample_cap: f64,
    pub cost_transform: bool,
    pub seed: u64,
}

impl Default for CdtSettings {
    fn default() -> Self {
        CdtSettings {
            embedding_dim: 128,
            num_layers: 3,
            num_heads: 8,
            seq_len: 10,
            dropout: 0.1,
            batch_size: 2048,
            lr: 1e-4,
            weight_decay: 1e-4,
            clip_grad: 0.25,
            warmup_steps: 500,
            reward_scale: 0.1,
            cost_scale: 1.0,
            loss_cost_weight: 0.02,
            init_temperature: 0.1,
            cost_sample_cap: 70.0,
            cost_transform: true,
            seed: 0,
        }
    }
}

/// OSRL's per-task CDT config line of `data/cdt_targets.csv`, split.
fn task_config(task: &str) -> anyhow::Result<Vec<&'static str>> {
    let csv = include_str!("../../data/cdt_targets.csv");
    let line = csv
        .lines()
        .find(|l| l.split(',').next() == Some(task))
        .ok_or_else(|| anyhow::anyhow!("data/cdt_targets.csv has no CDT config for {task}"))?;
    let fields: Vec<&str> = line.split(',').collect();
    anyhow::ensure!(fields.len() == 9, "malformed CDT config line: {line}");
    Ok(fields)
}

/// OSRL's per-task augmentation constants (`deg`, `max_reward`, `min_reward`, `max_rew_decrease`).
pub fn task_augmentation(task: &str) -> anyhow::Result<Augmentation> {
    let f = task_config(task)?;
    Ok(Augmentation::osrl(
        f[5].parse()?,
        f[6].parse()?,
        f[7].parse()?,
        f[8].parse()?,
    ))
}

/// OSRL's per-task `target_returns` (reward; cost), in threshold order (`data/cdt_targets.csv`).
pub fn return_targets(task: &str) -> anyhow::Result<Vec<(f64, f64)>> {
    let field = task_config(task)?[4];
    field
        .split_whitespace()
        .map(|pair| {
            let (r, c) = pair
                .trim_matches(|c| c == '(' || c == ')')
                .split_once(';')
                .ok_or_else(|| anyhow::anyhow!("malformed CDT target {pair} for {task}"))?;
            Ok((r.parse()?, c.parse()?))
        })
        .collect()
}

/// A trajectory as training sees it: an episode of the data, its reward- and cost-to-go shifted by a relabelling
/// (0 for the original).
#[derive(Debug, Clone, Copy)]
struct Trajectory {
    episode: usize,
    reward_shift: f32,
    cost_shift: f32,
    cost_return: f64,
}

/// A batch of windows as the model reads them: `[batch, seq_len, …]`, returns scaled, cost labels 0/1.
pub struct Windows {
    pub states: Tensor,
    pub actions: Tensor,
    pub returns_to_go: Tensor,
    pub costs_to_go: Tensor,
    /// u32 timesteps within the episode.
    pub timesteps: Tensor,
    pub mask: Tensor,
    pub cost_labels: Tensor,
}

pub struct CdtLearner {
    pub settings: CdtSettings,
    pub model: Cdt,
    optim: Adam,
    log_temperature: Var,
    temperature_optim: Adam,
    data: Demonstrations,
    /// Per row: reward- and cost-to-go (undiscounted) within its trajectory.
    returns_to_go: Vec<f32>,
    costs_to_go: Vec<f32>,
    /// The trajectories windows are drawn from: every episode of the data, then the relabelled copies.
    trajectories: Vec<Trajectory>,
    /// How many of them are relabelled copies (recorded).
    pub augmented: usize,
    /// Cumulative sampling weights over the trajectories.
    cumulative: Vec<f64>,
    /// How trajectories are drawn (recorded: uniform when no trajectory is below the cap).
    pub sampling: String,
    steps: u64,
    noise: Noise,
    device: Device,
}

impl CdtLearner {
    /// A learner for a task whose episodes last at most `episode_len` steps, with OSRL's return augmentation when
    /// `augmentation` is given.
    pub fn new(
        settings: CdtSettings,
        data: Demonstrations,
        episode_len: usize,
        augmentation: Option<&Augmentation>,
    ) -> anyhow::Result<Self> {
        Self::on_device(settings, data, episode_len, augmentation, &Device::Cpu)
    }

    /// As [`CdtLearner::new`], training on `device` (the model initialised on the CPU from the seed, then moved;
    /// windows are cut on the host and copied over).
    pub fn on_device(
        settings: CdtSettings,
        data: Demonstrations,
        episode_len: usize,
        augmentation: Option<&Augmentation>,
        device: &Device,
    ) -> anyhow::Result<Self> {
        anyhow::ensure!(!data.episodes.is_empty(), "no trajectories to learn from");
        if let Some(&(_, len, _, _)) = data.episodes.iter().find(|e| e.1 > episode_len) {
            anyhow::bail!("a trajectory of {len} steps is longer than the task's {episode_len}-step episodes");
        }
        let mut noise = Noise::seeded(settings.seed);
        let shape = CdtShape {
            obs_dim: data.obs_dim,
            act_dim: data.act_dim,
            embedding_dim: settings.embedding_dim,
            num_layers: settings.num_layers,
            num_heads: settings.num_heads,
            seq_len: settings.seq_len,
            episode_len,
        };
        let model = Cdt::new(shape, settings.cost_transform, &mut noise)?.to_device(device)?;
        let (mut returns_to_go, mut costs_to_go) = (vec![0f32; data.rows()], vec![0f32; data.rows()]);
        for &(start, len, _, _) in &data.episodes {
            let (mut r, mut c) = (0f64, 0f64);
            for row in (start..start + len).rev() {
                r += f64::from(data.rewards[row]);
                c += f64::from(data.costs[row]);
                returns_to_go[row] = r as f32;
                costs_to_go[row] = c as f32;
            }
        }
        let mut trajectories: Vec<Trajectory> = data
            .episodes
            .iter()
            .enumerate()
            .map(|(episode, e)| Trajectory {
                episode,
                reward_shift: 0.0,
                cost_shift: 0.0,
                cost_return: e.3,
            })
            .collect();
        let points: Vec<(f64, f64)> = data.episodes.iter().map(|e| (e.3, e.2)).collect();
        let relabelled = augmentation.map_or_else(Vec::new, |a| augment(&points, a, &mut noise));
        let augmented = relabelled.len();
        trajectories.extend(relabelled.iter().map(|r| Trajectory {
            episode: r.trajectory,
            reward_shift: (r.reward_return - points[r.trajectory].1) as f32,
            cost_shift: (r.cost_return - points[r.trajectory].0) as f32,
            cost_return: r.cost_return,
        }));
        let weights: Vec<f64> = trajectories
            .iter()
            .map(|t| (settings.cost_sample_cap - t.cost_return).max(0.0))
            .collect();
        let uniform = weights.iter().all(|&w| w == 0.0);
        let sampling = if uniform {
            format!(
                "uniform: no trajectory has a cost return below {}, so OSRL's max(0, {} − C) weights are all 0",
                settings.cost_sample_cap, settings.cost_sample_cap
            )
        } else {
            format!("∝ max(0, {} − cost return)", settings.cost_sample_cap)
        };
        let cumulative = weights
            .iter()
            .map(|&w| if uniform { 1.0 } else { w })
            .scan(0.0, |acc, w| {
                *acc += w;
                Some(*acc)
            })
            .collect();
        let log_temperature = Var::from_vec(vec![settings.init_temperature.ln() as f32], 1, device)?;
        Ok(CdtLearner {
            optim: Adam::adamw(
                model.named_vars(),
                settings.lr,
                settings.weight_decay,
                Some(settings.clip_grad),
            )?,
            temperature_optim: Adam::new(vec![("log_temperature".into(), log_temperature.clone())], 1e-4, None)?,
            log_temperature,
            model,
            data,
            returns_to_go,
            costs_to_go,
            trajectories,
            augmented,
            cumulative,
            sampling,
            steps: 0,
            noise,
            device: device.clone(),
            settings,
        })
    }

    /// The optimizers under OSRL's names (`optim`: AdamW over the model; `log_temperature_optimizer`), the
    /// temperature's variable and the random numbers (dropout masks, window draws): for tests/parity.
    pub fn optimizers(&mut self) -> Vec<(&'static str, &mut Adam)> {
        vec![
            ("optim", &mut self.optim),
            ("log_temperature_optimizer", &mut self.temperature_optim),
        ]
    }

    pub fn log_temperature(&self) -> &Var {
        &self.log_temperature
    }

    pub fn noise(&mut self) -> &mut Noise {
        &mut self.noise
    }

    /// A trajectory drawn by the sampling weights.
    fn draw_trajectory(&mut self) -> usize {
        let total = *self.cumulative.last().expect("at least one trajectory");
        let u = self.noise.uniform() * total;
        self.cumulative
            .partition_point(|&c| c <= u)
            .min(self.cumulative.len() - 1)
    }

    /// One gradient step on a freshly drawn batch of windows.
    pub fn step(&mut self) -> anyhow::Result<Figures> {
        let windows = self.sample()?;
        self.update(&windows)
    }

    /// A batch of `seq_len`-step windows: trajectories drawn by the sampling weights, a uniform start in each, zero
    /// padding past the trajectory's end (masked out).
    pub fn sample(&mut self) -> anyhow::Result<Windows> {
        let s = self.settings.clone();
        let (b, k) = (s.batch_size, s.seq_len);
        let (o, a) = (self.data.obs_dim, self.data.act_dim);
        let mut states = vec![0f32; b * k * o];
        let mut actions = vec![0f32; b * k * a];
        let (mut rtg, mut ctg, mut mask, mut labels) = (
            vec![0f32; b * k],
            vec![0f32; b * k],
            vec![0f32; b * k],
            vec![0f32; b * k],
        );
        let mut timesteps = vec![0u32; b * k];
        for i in 0..b {
            let drawn = self.draw_trajectory();
            let trajectory = self.trajectories[drawn];
            let (first, len, _, _) = self.data.episodes[trajectory.episode];
            let start = (self.noise.next_u64() % len as u64) as usize;
            for j in 0..k {
                let at = i * k + j;
                timesteps[at] = (start + j) as u32;
                if start + j >= len {
                    continue;
                }
                let row = first + start + j;
                states[at * o..(at + 1) * o].copy_from_slice(&self.data.observations[row * o..(row + 1) * o]);
                actions[at * a..(at + 1) * a].copy_from_slice(&self.data.actions[row * a..(row + 1) * a]);
                rtg[at] = (self.returns_to_go[row] + trajectory.reward_shift) * s.reward_scale as f32;
                ctg[at] = (self.costs_to_go[row] + trajectory.cost_shift) * s.cost_scale as f32;
                mask[at] = 1.0;
                // OSRL's `cost.long()`: the class is the step's cost truncated (0 or 1 on every task's per-step costs;
                // clamped to the head's two classes for MetaDrive's fractional ones).
                labels[at] = self.data.costs[row].trunc().clamp(0.0, 1.0);
            }
        }
        let device = &self.device;
        Ok(Windows {
            states: Tensor::from_vec(states, (b, k, o), device)?,
            actions: Tensor::from_vec(actions, (b, k, a), device)?,
            returns_to_go: Tensor::from_vec(rtg, (b, k), device)?,
            costs_to_go: Tensor::from_vec(ctg, (b, k), device)?,
            timesteps: Tensor::from_vec(timesteps, (b, k), device)?,
            mask: Tensor::from_vec(mask, (b, k), device)?,
            cost_labels: Tensor::from_vec(labels, (b, k), device)?,
        })
    }

    /// One gradient step on `windows`: the model (AdamW, OSRL's warm-up and clipping), then the temperature.
    pub fn update(&mut self, windows: &Windows) -> anyhow::Result<Figures> {
        let s = self.settings.clone();
        let (b, k, a) = windows.actions.dims3()?;
        let (actions, mask, labels) = (&windows.actions, &windows.mask, &windows.cost_labels);
        let mut training = Training {
            p: s.dropout,
            noise: &mut self.noise,
        };
        let (mu, log_std, cost_logits) = self.model.training_heads(
            &windows.states,
            actions,
            &windows.returns_to_go,
            &windows.costs_to_go,
            &windows.timesteps,
            &mut training,
        )?;
        let half_ln_tau = 0.5 * (2.0 * std::f64::consts::PI).ln();
        let mask3 = mask.unsqueeze(2)?.broadcast_as((b, k, a))?;
        let valid = mask3.sum_all()?.to_scalar::<f32>()?.max(1.0) as f64;
        let z = actions.sub(&mu)?.div(&log_std.exp()?)?;
        let log_prob = z.sqr()?.affine(-0.5, -half_ln_tau)?.sub(&log_std)?;
        let log_likelihood = log_prob.mul(&mask3)?.sum_all()?.affine(1.0 / valid, 0.0)?;
        let entropy = log_std
            .affine(1.0, 0.5 + half_ln_tau)?
            .mul(&mask3)?
            .sum_all()?
            .affine(1.0 / valid, 0.0)?;
        let temperature = f64::from(self.log_temperature.as_tensor().exp()?.to_vec1::<f32>()?[0]);
        let action_loss = log_likelihood.add(&entropy.affine(temperature, 0.0)?)?.neg()?;
        let log_classes = log_softmax(&cost_logits, 2)?;
        let picked = log_classes
            .narrow(2, 0, 1)?
            .squeeze(2)?
            .mul(&labels.affine(-1.0, 1.0)?)?
            .add(&log_classes.narrow(2, 1, 1)?.squeeze(2)?.mul(labels)?)?;
        let cost_loss = picked.neg()?.mul(mask)?.mean_all()?;
        let loss = action_loss.add(&cost_loss.affine(s.loss_cost_weight, 0.0)?)?;
        // LambdaLR(min((step + 1)/warmup, 1)): the factor of the step about to be taken.
        self.optim.lr = s.lr * ((self.steps + 1) as f64 / s.warmup_steps.max(1) as f64).min(1.0);
        let grad_norm = self.optim.step(&loss.backward()?)?;

        let entropy_now = f64::from(entropy.to_scalar::<f32>()?);
        let target_entropy = -(a as f64);
        let temperature_loss = self
            .log_temperature
            .as_tensor()
            .exp()?
            .affine(entropy_now - target_entropy, 0.0)?
            .sum_all()?;
        self.temperature_optim.step(&temperature_loss.backward()?)?;
        self.steps += 1;
        Ok(vec![
            ("loss", f64::from(loss.to_scalar::<f32>()?)),
            ("action", f64::from(action_loss.to_scalar::<f32>()?)),
            ("cost", f64::from(cost_loss.to_scalar::<f32>()?)),
            ("entropy", entropy_now),
            ("temperature", temperature),
            ("grad_norm", grad_norm),
            ("lr", self.optim.lr),
        ])
    }

    /// Writes the model with one (reward, cost) return target per threshold of `thresholds` (in order).
    pub fn write(
        &self,
        dir: &Path,
        task: &str,
        thresholds: &[f64],
        targets: &[(f64, f64)],
        training: serde_json::Value,
    ) -> anyhow::Result<()> {
        anyhow::ensure!(
            thresholds.len() == targets.len(),
            "{} thresholds but {} CDT targets",
            thresholds.len(),
            targets.len()
        );
        let shape = self.model.shape;
        let config = PolicyConfig {
            format: checkpoint::FORMAT.into(),
            task: task.to_owned(),
            obs_dim: shape.obs_dim,
            act_dim: shape.act_dim,
            architecture: Architecture::Cdt {
                embedding_dim: shape.embedding_dim,
                num_layers: shape.num_layers,
                num_heads: shape.num_heads,
                seq_len: shape.seq_len,
                episode_len: shape.episode_len,
                max_action: MAX_ACTION,
                reward_scale: self.settings.reward_scale,
                cost_scale: self.settings.cost_scale,
                cost_transform: self.settings.cost_transform,
            },
            observation_normalization: None,
            conditioning: Conditioning::ReturnsToGo {
                targets: thresholds
                    .iter()
                    .zip(targets)
                    .map(|(&cost_threshold, &(reward_return, cost_return))| ReturnTarget {
                        cost_threshold,
                        reward_return,
                        cost_return,
                    })
                    .collect(),
            },
            training: Some(training),
        };
        checkpoint::write(dir, &config, &dsrl_policy::tensors_of(self.model.named_vars()))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use dsrl_policy::DType;

    use super::*;
    use crate::offline::tests::{figure, first_weights, toy};

    fn small(seed: u64) -> CdtSettings {
        CdtSettings {
            embedding_dim: 16,
            num_layers: 1,
            num_heads: 2,
            seq_len: 4,
            batch_size: 16,
            warmup_steps: 5,
            lr: 1e-3,
            seed,
            ..CdtSettings::default()
        }
    }

    #[test]
    fn osrls_targets_are_read_per_task_in_threshold_order() {
        assert_eq!(
            return_targets("OfflineCarCircle-v0").unwrap(),
            vec![(450.0, 10.0), (500.0, 20.0), (550.0, 50.0)]
        );
        assert_eq!(
            return_targets("OfflineCarCircle1Gymnasium-v0").unwrap()[1],
            (22.5, 40.0)
        );
        assert!(return_targets("NoSuchTask").is_err());
    }

    #[test]
    fn training_lowers_the_loss_deterministically_warms_up_and_writes_what_the_evaluator_plays() {
        let mut learner = CdtLearner::new(small(2), toy(), 10, Some(&Augmentation::osrl(1, 12.0, 1.0, 5.0))).unwrap();
        assert!(learner.sampling.starts_with('∝'), "{}", learner.sampling);
        assert!(learner.augmented > 0, "relabelled copies join the data");
        let first = learner.step().unwrap();
        // The warm-up: the first step runs at 1/5 of the rate.
        assert!((figure(&first, "lr") - 2e-4).abs() < 1e-12);
        let mut last = first.clone();
        for _ in 0..40 {
            last = learner.step().unwrap();
        }
        assert_eq!(figure(&last, "lr"), 1e-3);
        for (n, v) in &last {
            assert!(v.is_finite(), "{n}");
        }
        assert!(figure(&last, "loss") < figure(&first, "loss"), "{first:?} -> {last:?}");
        // The temperature moved from 0.1.
        assert!((figure(&last, "temperature") - 0.1).abs() > 1e-6);

        let mut again = CdtLearner::new(small(2), toy(), 10, Some(&Augmentation::osrl(1, 12.0, 1.0, 5.0))).unwrap();
        for _ in 0..41 {
            again.step().unwrap();
        }
        // [0] is the timestep embedding; [1] a linear layer, as before.
        assert_eq!(
            first_weights(learner.model.named_vars().split_off(1)),
            first_weights(again.model.named_vars().split_off(1))
        );

        // The evaluator plays the written model: its first action from the target (R̂, Ĉ) is the model's mean.
        let dir = tempfile::tempdir().unwrap();
        learner
            .write(
                dir.path(),
                "toy",
                &[10.0, 20.0],
                &[(8.0, 0.0), (9.0, 5.0)],
                serde_json::json!({}),
            )
            .unwrap();
        let (config, tensors) = checkpoint::read(dir.path()).unwrap();
        let policy = dsrl_policy::Policy::load(&config, &tensors).unwrap();
        let mut rollout = policy.rollout(20.0, 1).unwrap();
        rollout.start_episode(0, 7).unwrap();
        let obs = [0.3f32, 0.7];
        let played = rollout.act(&[0], &obs).unwrap();
        let cpu = &Device::Cpu;
        let mean = learner
            .model
            .action_means(
                &Tensor::from_vec(obs.to_vec(), (1, 1, 2), cpu).unwrap(),
                &Tensor::zeros((1, 1, 1), DType::F32, cpu).unwrap(),
                &Tensor::new(&[[0.9f32]], cpu).unwrap(),
                &Tensor::new(&[[5.0f32]], cpu).unwrap(),
                &Tensor::new(&[[0u32]], cpu).unwrap(),
            )
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert!(
            (played[0] - mean[0].clamp(-1.0, 1.0)).abs() < 1e-5,
            "{played:?} vs {mean:?}"
        );
        // A target per threshold, or nothing is written.
        assert!(
            learner
                .write(dir.path(), "toy", &[10.0], &[], serde_json::json!({}))
                .is_err()
        );
    }
}
