//! CAPS, constraint-adaptive policy switching (Chemingui et al., AAAI 2025; the IQL variant, `capsiql.py`): several
//! policy heads on one shared trunk, each trained for another reward/cost trade-off, and two critics (reward Q and
//! cost Q, each a pair answering its minimum). At deploy time, at every step, the policy takes each head's action,
//! keeps the heads whose predicted cost fits what is left of the episode's budget, and plays the one among them with
//! the highest predicted reward; when none fits, the one with the lowest predicted cost. One checkpoint serves every
//! budget, without retraining.
//!
//! What is left of the budget is spread over the remaining steps as the cost-Q of a constant per-step cost would
//! be: with `B` the budget minus the (scaled) cost received so far, `t` the step and `L` the episode length, the
//! limit is `max(B, 0)·(1 − γ^{L−t}) / (1 − γ) / (L − t)` (CAPS's `rollout_switch`).
//!
//! Tensors: the trunk `actor.trunk.<i>` (`[obs, hidden..]`, ReLU after every layer), heads `actor.head.<k>.0`
//! (`[hidden, act]`, `max_action · tanh`), critics `reward_q.<j>.<i>` and `cost_q.<j>.<i>` (`[obs + act, hidden..,
//! 1]`, ReLU; `j` ∈ {0, 1}). The cost critic is trained on negated costs, as CAPS's is, so the predicted cost is
//! `−min(cost_q)`.

use candle_core::Tensor;

use crate::layers::Weights;
use crate::mlp::{Activation, Mlp};
use crate::noise::Noise;
use crate::offline::{Ensemble, qc_threshold};
use crate::{PolicyError, Result};

/// The sizes and constants of a CAPS policy.
#[derive(Debug, Clone, PartialEq)]
pub struct CapsShape {
    pub obs_dim: usize,
    pub act_dim: usize,
    pub hidden_sizes: Vec<usize>,
    pub num_heads: usize,
}

/// The networks CAPS deploys (training adds the value networks and target copies).
pub struct CapsNetworks {
    pub shape: CapsShape,
    pub trunk: Mlp,
    pub heads: Vec<Mlp>,
    /// Pairs answering their minimum (OSRL's `Ensemble` of two, named `reward_q.<j>`, `cost_q.<j>`).
    pub reward_q: Ensemble,
    pub cost_q: Ensemble,
}

fn critic_sizes(shape: &CapsShape) -> Vec<usize> {
    let mut sizes = vec![shape.obs_dim + shape.act_dim];
    sizes.extend(&shape.hidden_sizes);
    sizes.push(1);
    sizes
}

fn trunk_sizes(shape: &CapsShape) -> Vec<usize> {
    let mut sizes = vec![shape.obs_dim];
    sizes.extend(&shape.hidden_sizes);
    sizes
}

impl CapsShape {
    fn check(&self) -> Result<usize> {
        let last = *self
            .hidden_sizes
            .last()
            .ok_or_else(|| PolicyError::Format("caps needs at least one hidden layer".into()))?;
        if !(1..=64).contains(&self.num_heads) {
            return Err(PolicyError::Format(format!(
                "caps: num_heads = {} must be in 1..=64",
                self.num_heads
            )));
        }
        Ok(last)
    }
}

impl CapsNetworks {
    /// Initialised as PyTorch's `nn.Linear` default, which CAPS keeps.
    pub fn new(shape: CapsShape, noise: &mut Noise) -> Result<CapsNetworks> {
        Self::build(shape, |prefix, sizes| {
            Mlp::pytorch_default(prefix, sizes, Activation::Relu, noise)
        })
    }

    /// Reads the deployed networks of `shape`, checking every name and size.
    pub fn from_weights(shape: CapsShape, w: &mut Weights) -> Result<CapsNetworks> {
        Self::build(shape, |prefix, sizes| w.mlp(prefix, sizes, Activation::Relu))
    }

    /// The networks of `shape`, each made by `make(prefix, layer sizes)`.
    fn build(shape: CapsShape, mut make: impl FnMut(&str, &[usize]) -> Result<Mlp>) -> Result<CapsNetworks> {
        let last = shape.check()?;
        let trunk = make("actor.trunk", &trunk_sizes(&shape))?;
        let heads = (0..shape.num_heads)
            .map(|k| make(&format!("actor.head.{k}"), &[last, shape.act_dim]))
            .collect::<Result<_>>()?;
        let critic = critic_sizes(&shape);
        let reward_q = Ensemble {
            nets: vec![make("reward_q.0", &critic)?, make("reward_q.1", &critic)?],
        };
        let cost_q = Ensemble {
            nets: vec![make("cost_q.0", &critic)?, make("cost_q.1", &critic)?],
        };
        Ok(CapsNetworks {
            shape,
            trunk,
            heads,
            reward_q,
            cost_q,
        })
    }

    pub fn named_vars(&self) -> Vec<(String, candle_core::Var)> {
        let mut out = self.actor_vars();
        out.extend(self.reward_q.named_vars());
        out.extend(self.cost_q.named_vars());
        out
    }

    /// The trunk's and the heads' variables (what the actor's optimizer steps).
    pub fn actor_vars(&self) -> Vec<(String, candle_core::Var)> {
        let mut out = self.trunk.named_vars();
        for head in &self.heads {
            out.extend(head.named_vars());
        }
        out
    }

    /// Each head's mean action `tanh(head(relu(trunk(obs))))` (before `max_action`), `[batch, act]` per head.
    pub fn head_means(&self, obs: &Tensor) -> Result<Vec<Tensor>> {
        let h = crate::fused::relu(&self.trunk.forward(obs)?)?;
        self.heads.iter().map(|head| Ok(head.forward(&h)?.tanh()?)).collect()
    }

    /// The actions CAPS plays at `obs` (`[n, obs]`) given each row's per-step cost limit, row-major `[n, act]`:
    /// among the heads whose predicted cost is below the limit the one with the highest predicted reward, else
    /// the one with the lowest predicted cost.
    pub fn switch(&self, obs: &Tensor, limits: &[f64], max_action: f64) -> Result<Vec<f32>> {
        let (n, _) = obs.dims2()?;
        let (k, a) = (self.shape.num_heads, self.shape.act_dim);
        if limits.len() != n {
            return Err(PolicyError::Format(format!(
                "caps: {} limits for {n} rows",
                limits.len()
            )));
        }
        let actions = self
            .head_means(obs)?
            .iter()
            .map(|m| m.affine(max_action, 0.0))
            .collect::<candle_core::Result<Vec<_>>>()?;
        // Head-major rows: head j's action for row i is row j·n + i.
        let stacked = Tensor::cat(&actions, 0)?;
        let input = Tensor::cat(&[&Tensor::cat(&vec![obs; k], 0)?, &stacked], 1)?;
        let reward: Vec<f32> = Ensemble::min(&self.reward_q.values(&input)?)?.to_vec1()?;
        let cost: Vec<f32> = Ensemble::min(&self.cost_q.values(&input)?)?.neg()?.to_vec1()?;
        let stacked: Vec<f32> = stacked.flatten_all()?.to_vec1()?;
        let mut out = Vec::with_capacity(n * a);
        for (i, &limit) in limits.iter().enumerate() {
            let heads: Vec<(f32, f32)> = (0..k).map(|j| (reward[j * n + i], cost[j * n + i])).collect();
            let chosen = choose_head(&heads, limit);
            let row = chosen * n + i;
            out.extend_from_slice(&stacked[row * a..(row + 1) * a]);
        }
        Ok(out)
    }

    pub fn to_device(self, device: &candle_core::Device) -> Result<CapsNetworks> {
        Ok(CapsNetworks {
            trunk: self.trunk.to_device(device)?,
            heads: self
                .heads
                .into_iter()
                .map(|h| h.to_device(device))
                .collect::<Result<_>>()?,
            reward_q: self.reward_q.to_device(device)?,
            cost_q: self.cost_q.to_device(device)?,
            ..self
        })
    }
}

/// CAPS's `select_head_q`: of heads given as `(predicted reward, predicted cost)`, the first with the highest
/// reward among those whose cost is below `limit`; when none is, the first with the lowest cost.
pub fn choose_head(heads: &[(f32, f32)], limit: f64) -> usize {
    let (mut fitting, mut cheapest): (Option<usize>, usize) = (None, 0);
    for (j, &(reward, cost)) in heads.iter().enumerate() {
        if f64::from(cost) < limit && fitting.is_none_or(|f| reward > heads[f].0) {
            fitting = Some(j);
        }
        if cost < heads[cheapest].1 {
            cheapest = j;
        }
    }
    fitting.unwrap_or(cheapest)
}

/// The per-step cost limit at step `step` of an episode of `episode_len` steps with `remaining` of the budget left:
/// OSRL's per-step cost threshold ([`qc_threshold`]) of what is left, over the steps left.
pub fn per_step_limit(remaining: f64, step: usize, episode_len: usize, gamma: f64) -> f64 {
    // Past the declared length (an evaluator horizon longer than training's), the last step's spreading holds.
    let left = episode_len.saturating_sub(step).max(1);
    if (1.0 - gamma).abs() < 1e-12 {
        // The limit of the spreading as γ → 1: the remainder shared evenly, discounting nothing.
        return remaining.max(0.0);
    }
    qc_threshold(remaining.max(0.0), gamma, left)
}

#[cfg(test)]
mod tests {
    use candle_core::Device;

    use super::*;

    fn matrix(values: Vec<f32>, rows: usize, cols: usize) -> Result<Tensor> {
        Ok(Tensor::from_vec(values, (rows, cols), &Device::Cpu)?)
    }

    #[test]
    fn the_switch_plays_the_best_reward_that_fits_else_the_least_cost() {
        let heads = [(1.0f32, 5.0f32), (3.0, 2.0), (2.0, 0.5), (9.0, 8.0)];
        // Limit 3: heads 1 and 2 fit; head 1 has the higher reward.
        assert_eq!(choose_head(&heads, 3.0), 1);
        // Limit 1: only head 2 fits.
        assert_eq!(choose_head(&heads, 1.0), 2);
        // Limit 10: every head fits; head 3 has the highest reward.
        assert_eq!(choose_head(&heads, 10.0), 3);
        // Limit 0.1: none fits; head 2 has the lowest cost. Strictly below: a cost equal to the limit does not fit.
        assert_eq!(choose_head(&heads, 0.1), 2);
        assert_eq!(choose_head(&heads, 0.5), 2);
        assert_eq!(choose_head(&[(1.0, 0.5), (2.0, 0.5)], 0.5), 0);
    }

    #[test]
    fn the_budget_left_is_spread_over_the_steps_left_as_a_discounted_constant_cost() {
        // γ = 0.5, 2 steps left, 3 left of the budget: 3 · (1 − 0.25) / 0.5 / 2 = 2.25.
        assert!((per_step_limit(3.0, 8, 10, 0.5) - 2.25).abs() < 1e-12);
        // The last step: the whole remainder.
        assert!((per_step_limit(3.0, 9, 10, 0.99) - 3.0).abs() < 1e-12);
        // An overspent budget allows nothing; steps past the length act as the last.
        assert_eq!(per_step_limit(-2.0, 0, 10, 0.99), 0.0);
        assert!((per_step_limit(3.0, 15, 10, 0.99) - 3.0).abs() < 1e-12);
    }

    #[test]
    fn switching_picks_per_row_and_plays_the_chosen_heads_action() {
        let shape = CapsShape {
            obs_dim: 3,
            act_dim: 2,
            hidden_sizes: vec![8, 8],
            num_heads: 3,
        };
        let nets = CapsNetworks::new(shape, &mut Noise::seeded(4)).unwrap();
        let mut noise = Noise::seeded(5);
        let obs = matrix(noise.normals_f32(6), 2, 3).unwrap();
        let means: Vec<Vec<Vec<f32>>> = nets
            .head_means(&obs)
            .unwrap()
            .iter()
            .map(|m| m.to_vec2().unwrap())
            .collect();
        let mut predicted = Vec::new();
        for (j, m) in means.iter().enumerate() {
            let acts = matrix(m.iter().flatten().map(|v| v * 2.0).collect(), 2, 2).unwrap();
            let input = Tensor::cat(&[&obs, &acts], 1).unwrap();
            let r: Vec<f32> = Ensemble::min(&nets.reward_q.values(&input).unwrap())
                .unwrap()
                .to_vec1()
                .unwrap();
            let c: Vec<f32> = Ensemble::min(&nets.cost_q.values(&input).unwrap())
                .unwrap()
                .neg()
                .unwrap()
                .to_vec1()
                .unwrap();
            predicted.push((j, r, c));
        }
        for limits in [[-1e9, -1e9], [1e9, 1e9], [1e9, -1e9]] {
            let played = nets.switch(&obs, &limits, 2.0).unwrap();
            for (i, &limit) in limits.iter().enumerate() {
                let heads: Vec<(f32, f32)> = predicted.iter().map(|(_, r, c)| (r[i], c[i])).collect();
                let want = choose_head(&heads, limit);
                let row: Vec<f32> = means[want][i].iter().map(|v| v * 2.0).collect();
                assert_eq!(&played[i * 2..i * 2 + 2], &row[..], "row {i} at limit {limit}");
            }
        }
    }
}
