//! CAPS-IQL (Chemingui et al., AAAI 2025; the authors' `capsiql.py` over OSRL): constraint-adaptive policy
//! switching on implicit Q-learning. Beyond the paper's baselines: one model for every cost budget, which adapts
//! within an episode to the cost it has received (the evaluator side is `dsrl_policy::caps`).
//!
//! Networks (hidden [512, 512], ReLU, PyTorch's default initialisation): value networks `V_r`, `V_c`; critic pairs
//! `Q_r`, `Q_c` with target copies; a trunk shared by `K` policy heads. The cost critic learns the **negated** cost,
//! so "higher is better" holds for both. One step, in CAPS's order:
//! 1. `V_r(s')`, `V_c(s')` for the backups, before any update;
//! 2. `V_r` by expectile regression (τ = 0.7) on `min Q_r'(s, a) − V_r(s)`, and `V_c` alike on the cost pair;
//!    these differences, before the update, are the advantages `A_r`, `A_c`;
//! 3. `Q_r` on `r + γ(1 − d)·V_r(s')`, `Q_c` on `−c + γ(1 − d)·V_c(s')` (mean of the pair's squared errors);
//! 4. the heads by advantage-weighted regression on the data's actions, `w·(−log N(a | tanh(head_k), 1))` with
//!    `w = min(e^{β A_r}, 100)` for head 0, `min(e^{β_c A_c}, 100)` for the last head and
//!    `e^{β A_r} + (k / ((K − 1)/2))·e^{β_c A_c}` (each clamped) between, averaged over heads; the actor's learning
//!    rate follows a cosine over `max_steps` (10⁶, not the 10⁵ trained: CAPS's config);
//! 5. soft target updates (τ = 0.005).
//!
//! As in CAPS's code, each head's log σ is a plain parameter list outside the module, never optimised, so σ = 1 and
//! the regression is a weighted squared error plus a constant. The hyperparameters are CAPS's defaults
//! (`capsiql_configs.py`: lrs 3e-4, batch 512, reward scale 0.1, cost scale 1, β = β_c = 3, τ_IQL = 0.7) with
//! 5 heads, the setting of its README's example (the config's default is 2).

use std::path::Path;

use dsrl_policy::Tensor;
use dsrl_policy::adam::Adam;
use dsrl_policy::caps::{CapsNetworks, CapsShape};
use dsrl_policy::checkpoint::{self, Architecture, Conditioning, PolicyConfig};
use dsrl_policy::mlp::{Activation, Mlp};
use dsrl_policy::noise::Noise;
use dsrl_policy::offline::{Ensemble, concat, soft_update};

use crate::offline::{Batch, EveryThresholdLearner, Figures, Transitions, expectile_loss};
use crate::{Demonstrations, MAX_ACTION};

/// Clamp on the exponentiated advantages (CAPS's `EXP_ADV_MAX`, `EXP_ADVC_MAX`).
const EXP_ADV_MAX: f64 = 100.0;

/// CAPS-IQL's configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct CapsSettings {
    pub hidden_sizes: Vec<usize>,
    pub num_heads: usize,
    /// Expectiles of the reward and cost value regressions.
    pub iql_tau: f64,
    pub iql_tau_cost: f64,
    /// Inverse temperatures of the reward and cost advantage weights.
    pub beta: f64,
    pub beta_cost: f64,
    pub tau: f64,
    pub gamma: f64,
    pub actor_lr: f64,
    pub q_lr: f64,
    pub value_lr: f64,
    /// The cosine schedule's horizon for the actor's learning rate.
    pub max_steps: u64,
    pub reward_scale: f64,
    pub cost_scale: f64,
    pub batch_size: usize,
    pub seed: u64,
}

impl Default for CapsSettings {
    fn default() -> Self {
        CapsSettings {
            hidden_sizes: vec![512, 512],
            num_heads: 5,
            iql_tau: 0.7,
            iql_tau_cost: 0.7,
            beta: 3.0,
            beta_cost: 3.0,
            tau: 0.005,
            gamma: 0.99,
            actor_lr: 3e-4,
            q_lr: 3e-4,
            value_lr: 3e-4,
            max_steps: 1_000_000,
            reward_scale: 0.1,
            cost_scale: 1.0,
            batch_size: 512,
            seed: 0,
        }
    }
}

pub struct CapsLearner {
    pub settings: CapsSettings,
    pub nets: CapsNetworks,
    reward_q_target: Ensemble,
    cost_q_target: Ensemble,
    reward_v: Mlp,
    cost_v: Mlp,
    actor_optim: Adam,
    reward_q_optim: Adam,
    cost_q_optim: Adam,
    reward_v_optim: Adam,
    cost_v_optim: Adam,
    noise: Noise,
    data: Transitions,
    episode_len: usize,
    steps: u64,
}

impl CapsLearner {
    /// A learner for a task whose episodes last `episode_len` steps (what deployment spreads the budget over).
    pub fn new(settings: CapsSettings, data: &Demonstrations, episode_len: usize) -> anyhow::Result<Self> {
        Self::on_device(settings, data, episode_len, &dsrl_policy::Device::Cpu)
    }

    /// As [`CapsLearner::new`], training on `device` (networks initialised on the CPU from the seed, then moved).
    pub fn on_device(
        settings: CapsSettings,
        data: &Demonstrations,
        episode_len: usize,
        device: &dsrl_policy::Device,
    ) -> anyhow::Result<Self> {
        let (o, a) = (data.obs_dim, data.act_dim);
        anyhow::ensure!(settings.num_heads >= 1, "caps needs at least one head");
        let mut noise = Noise::seeded(settings.seed);
        let shape = CapsShape {
            obs_dim: o,
            act_dim: a,
            hidden_sizes: settings.hidden_sizes.clone(),
            num_heads: settings.num_heads,
        };
        let nets = CapsNetworks::new(shape, &mut noise)?.to_device(device)?;
        let mut v_sizes = vec![o];
        v_sizes.extend(&settings.hidden_sizes);
        v_sizes.push(1);
        let reward_v = Mlp::pytorch_default("reward_v", &v_sizes, Activation::Relu, &mut noise)?.to_device(device)?;
        let cost_v = Mlp::pytorch_default("cost_v", &v_sizes, Activation::Relu, &mut noise)?.to_device(device)?;
        Ok(CapsLearner {
            actor_optim: Adam::new(nets.actor_vars(), settings.actor_lr, None)?,
            reward_q_optim: Adam::new(nets.reward_q.named_vars(), settings.q_lr, None)?,
            cost_q_optim: Adam::new(nets.cost_q.named_vars(), settings.q_lr, None)?,
            reward_v_optim: Adam::new(reward_v.named_vars(), settings.value_lr, None)?,
            cost_v_optim: Adam::new(cost_v.named_vars(), settings.value_lr, None)?,
            reward_q_target: nets.reward_q.copy()?,
            cost_q_target: nets.cost_q.copy()?,
            reward_v,
            cost_v,
            data: Transitions::new(data, device)?,
            nets,
            noise,
            episode_len,
            steps: 0,
            settings,
        })
    }

    /// The weight of head `k` of `heads` on each row, from the clamped exponentiated advantages.
    pub fn head_weight(k: usize, heads: usize, exp_adv_r: &Tensor, exp_adv_c: &Tensor) -> anyhow::Result<Tensor> {
        Ok(if k == 0 {
            exp_adv_r.clone()
        } else if k == heads - 1 {
            exp_adv_c.clone()
        } else {
            let coef = k as f64 / ((heads - 1) as f64 / 2.0);
            exp_adv_r.add(&exp_adv_c.affine(coef, 0.0)?)?
        })
    }

    /// The actor's learning rate at update `step` (PyTorch's `CosineAnnealingLR` to zero over `max_steps`).
    pub fn actor_lr(&self, step: u64) -> f64 {
        let s = &self.settings;
        let t = step.min(s.max_steps) as f64 / s.max_steps.max(1) as f64;
        s.actor_lr * (1.0 + (std::f64::consts::PI * t).cos()) / 2.0
    }

    pub fn update(&mut self, batch: &Batch) -> anyhow::Result<Figures> {
        let s = self.settings.clone();
        let input = concat(&batch.obs, &batch.act)?;
        let continues = batch.done.affine(-s.gamma, s.gamma)?;

        // 1. The backups' next-state values, before any update.
        let next_vr = self.reward_v.forward(&batch.next_obs)?.squeeze(1)?.detach();
        let next_vc = self.cost_v.forward(&batch.next_obs)?.squeeze(1)?.detach();

        // 2. Value networks by expectile regression; the advantages are taken before the update.
        let target_qr = Ensemble::min(&self.reward_q_target.values(&input)?)?.detach();
        let adv_r = target_qr.sub(&self.reward_v.forward(&batch.obs)?.squeeze(1)?)?;
        let reward_v_loss = expectile_loss(&adv_r, s.iql_tau)?;
        self.reward_v_optim.step(&reward_v_loss.backward()?)?;
        let target_qc = Ensemble::min(&self.cost_q_target.values(&input)?)?.detach();
        let adv_c = target_qc.sub(&self.cost_v.forward(&batch.obs)?.squeeze(1)?)?;
        let cost_v_loss = expectile_loss(&adv_c, s.iql_tau_cost)?;
        self.cost_v_optim.step(&cost_v_loss.backward()?)?;

        // 3. Critics: reward, and the negated cost.
        let reward_target = batch.reward.add(&continues.mul(&next_vr)?)?.detach();
        let reward_q_loss = Ensemble::mean_loss(&self.nets.reward_q.values(&input)?, &reward_target)?;
        self.reward_q_optim.step(&reward_q_loss.backward()?)?;
        let cost_target = batch.cost.neg()?.add(&continues.mul(&next_vc)?)?.detach();
        let cost_q_loss = Ensemble::mean_loss(&self.nets.cost_q.values(&input)?, &cost_target)?;
        self.cost_q_optim.step(&cost_q_loss.backward()?)?;

        // 4. The heads: advantage-weighted regression, each head on its own trade-off.
        let exp_adv_r = adv_r.detach().affine(s.beta, 0.0)?.exp()?.minimum(EXP_ADV_MAX)?;
        let exp_adv_c = adv_c.detach().affine(s.beta_cost, 0.0)?.exp()?.minimum(EXP_ADV_MAX)?;
        let heads = s.num_heads;
        let log_norm = 0.5 * (2.0 * std::f64::consts::PI).ln() * self.nets.shape.act_dim as f64;
        let mut actor_loss: Option<Tensor> = None;
        for (k, mean) in self.nets.head_means(&batch.obs)?.iter().enumerate() {
            // −log N(a | μ, 1) summed over the action's dimensions.
            let nll = mean.sub(&batch.act)?.sqr()?.sum(1)?.affine(0.5, log_norm)?;
            let weight = Self::head_weight(k, heads, &exp_adv_r, &exp_adv_c)?;
            let loss = weight.mul(&nll)?.mean_all()?.affine(1.0 / heads as f64, 0.0)?;
            actor_loss = Some(match actor_loss {
                None => loss,
                Some(total) => total.add(&loss)?,
            });
        }
        let actor_loss = actor_loss.expect("at least one head");
        self.actor_optim.lr = self.actor_lr(self.steps);
        self.actor_optim.step(&actor_loss.backward()?)?;
        self.steps += 1;

        // 5. Targets.
        soft_update(
            &self.reward_q_target.named_vars(),
            &self.nets.reward_q.named_vars(),
            s.tau,
        )?;
        soft_update(&self.cost_q_target.named_vars(), &self.nets.cost_q.named_vars(), s.tau)?;

        let scalar = |t: &Tensor| -> anyhow::Result<f64> { Ok(f64::from(t.to_scalar::<f32>()?)) };
        Ok(vec![
            ("reward_v", scalar(&reward_v_loss)?),
            ("cost_v", scalar(&cost_v_loss)?),
            ("reward_q", scalar(&reward_q_loss)?),
            ("cost_q", scalar(&cost_q_loss)?),
            ("actor", scalar(&actor_loss)?),
            ("actor_lr", self.actor_optim.lr),
        ])
    }
}

impl EveryThresholdLearner for CapsLearner {
    fn step(&mut self) -> anyhow::Result<Figures> {
        let s = &self.settings;
        let batch = self
            .data
            .sample(s.batch_size, s.reward_scale, s.cost_scale, &mut self.noise)?;
        self.update(&batch)
    }

    /// Writes the evaluator's `caps` checkpoint (trunk, heads, critic pairs; one model for every budget) with
    /// `training` recorded.
    fn write(&self, dir: &Path, task: &str, training: serde_json::Value) -> anyhow::Result<()> {
        let s = &self.settings;
        let config = PolicyConfig {
            format: checkpoint::FORMAT.into(),
            task: task.to_owned(),
            obs_dim: self.nets.shape.obs_dim,
            act_dim: self.nets.shape.act_dim,
            architecture: Architecture::Caps {
                hidden_sizes: s.hidden_sizes.clone(),
                num_heads: s.num_heads,
                max_action: MAX_ACTION,
                gamma: s.gamma,
                episode_len: self.episode_len,
                cost_scale: s.cost_scale,
            },
            observation_normalization: None,
            conditioning: Conditioning::CostBudget,
            training: Some(training),
        };
        checkpoint::write(dir, &config, &dsrl_policy::tensors_of(self.nets.named_vars()))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::offline::tests::{figure, first_weights, read_back, run_steps, toy};

    fn small(seed: u64) -> CapsSettings {
        CapsSettings {
            hidden_sizes: vec![16, 16],
            num_heads: 3,
            batch_size: 32,
            max_steps: 100,
            actor_lr: 3e-3,
            seed,
            ..CapsSettings::default()
        }
    }

    #[test]
    fn the_expectile_loss_weighs_positive_and_negative_errors_as_worked_by_hand() {
        let u = Tensor::new(&[2.0f32, -1.0], &dsrl_policy::Device::Cpu).unwrap();
        // (0.7·4 + 0.3·1) / 2 = 1.55
        let loss = expectile_loss(&u, 0.7).unwrap().to_scalar::<f32>().unwrap();
        assert!((loss - 1.55).abs() < 1e-6, "{loss}");
    }

    #[test]
    fn heads_span_reward_to_cost_and_the_actor_rate_follows_a_cosine() {
        let cpu = &dsrl_policy::Device::Cpu;
        let (r, c) = (
            Tensor::new(&[2.0f32], cpu).unwrap(),
            Tensor::new(&[10.0f32], cpu).unwrap(),
        );
        let weight = |k| -> f32 {
            CapsLearner::head_weight(k, 5, &r, &c)
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()[0]
        };
        // Head 0 reward only, head 4 cost only, head k between: r + (k/2)·c.
        assert_eq!(
            [weight(0), weight(1), weight(2), weight(3), weight(4)],
            [2.0, 7.0, 12.0, 17.0, 10.0]
        );
        let learner = CapsLearner::new(small(1), &toy(), 10).unwrap();
        assert!((learner.actor_lr(0) - 3e-3).abs() < 1e-15);
        assert!((learner.actor_lr(50) - 1.5e-3).abs() < 1e-12);
        assert!(learner.actor_lr(100).abs() < 1e-15);
    }

    #[test]
    fn a_few_steps_train_deterministically_and_the_checkpoint_switches_as_its_budget_runs_out() {
        let data = toy();
        let mut learner = CapsLearner::new(small(3), &data, 10).unwrap();
        // How far the heads are from the data's actions (the regression's unweighted error).
        let cpu = &dsrl_policy::Device::Cpu;
        let obs = Tensor::from_vec(data.observations[..200].to_vec(), (100, 2), cpu).unwrap();
        let act = Tensor::from_vec(data.actions[..100].to_vec(), (100, 1), cpu).unwrap();
        let imitation_error = |l: &CapsLearner| -> f32 {
            let heads = l.nets.head_means(&obs).unwrap();
            heads
                .iter()
                .map(|m| {
                    m.sub(&act)
                        .unwrap()
                        .sqr()
                        .unwrap()
                        .mean_all()
                        .unwrap()
                        .to_scalar::<f32>()
                        .unwrap()
                })
                .sum::<f32>()
        };
        let before = imitation_error(&learner);
        let (first, last) = run_steps(|| learner.step(), 100);
        assert!(
            figure(&last, "reward_q") < figure(&first, "reward_q"),
            "{first:?} -> {last:?}"
        );
        let after = imitation_error(&learner);
        assert!(after < 0.5 * before, "heads' error {before} -> {after}");
        let mut again = CapsLearner::new(small(3), &data, 10).unwrap();
        for _ in 0..100 {
            again.step().unwrap();
        }
        assert_eq!(
            first_weights(learner.nets.named_vars()),
            first_weights(again.nets.named_vars())
        );

        // Written, read back as the evaluator reads it, and played: one checkpoint at every budget.
        let (config, tensors, policy) = read_back(&learner, 80);
        assert_eq!(config.conditioning, Conditioning::CostBudget);
        let obs = [0.3f32, 0.7];
        let o = Tensor::from_vec(obs.to_vec(), (1, 2), &dsrl_policy::Device::Cpu).unwrap();
        let heads: Vec<f32> = learner
            .nets
            .head_means(&o)
            .unwrap()
            .iter()
            .map(|m| m.to_vec2::<f32>().unwrap()[0][0])
            .collect();
        let input = |a: f32| Tensor::new(&[[0.3f32, 0.7, a]], &dsrl_policy::Device::Cpu).unwrap();
        let predicted: Vec<(f32, f32)> = heads
            .iter()
            .map(|&a| {
                let r = Ensemble::min(&learner.nets.reward_q.values(&input(a)).unwrap()).unwrap();
                let c = Ensemble::min(&learner.nets.cost_q.values(&input(a)).unwrap())
                    .unwrap()
                    .neg()
                    .unwrap();
                (r.to_vec1::<f32>().unwrap()[0], c.to_vec1::<f32>().unwrap()[0])
            })
            .collect();
        for budget in [0.0, 5.0, 1e6] {
            let mut rollout = policy.rollout(budget, 1).unwrap();
            rollout.start_episode(0, 7).unwrap();
            let limit = dsrl_policy::caps::per_step_limit(budget, 0, 10, 0.99);
            let want = heads[dsrl_policy::caps::choose_head(&predicted, limit)];
            assert_eq!(rollout.act(&[0], &obs).unwrap(), vec![want], "budget {budget}");
        }
        // The cost received is taken off the budget: after spending it all, the policy plays as at budget 0.
        let mut spent = policy.rollout(5.0, 1).unwrap();
        spent.start_episode(0, 7).unwrap();
        spent.act(&[0], &obs).unwrap();
        spent.observe(&[0], &[1.0], &[5.0]).unwrap();
        let limit = dsrl_policy::caps::per_step_limit(0.0, 1, 10, 0.99);
        let want = heads[dsrl_policy::caps::choose_head(&predicted, limit)];
        assert_eq!(spent.act(&[0], &obs).unwrap(), vec![want]);

        // A caps checkpoint declared with another conditioning is refused, and so is cost_budget on another net.
        let mut wrong = config.clone();
        wrong.conditioning = Conditioning::PerThreshold { cost_threshold: 10.0 };
        let err = dsrl_policy::Policy::load(&wrong, &tensors).err().unwrap().to_string();
        assert!(err.contains("cost_budget goes with the caps architecture"), "{err}");
    }
}
