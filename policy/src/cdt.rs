//! OSRL's Constrained Decision Transformer (spec 5.4): each timestep is four tokens `[R̂_t, Ĉ_t, s_t, a_t]`
//! (reward-to-go, cost-to-go, state, action), each a linear embedding plus a learned timestep embedding; the
//! sequence goes through `LayerNorm`, pre-LN transformer blocks with causal multi-head attention, and a final
//! `LayerNorm`; the action is predicted from the output at the state token by a diagonal Gaussian head, whose mean
//! is the evaluated action. With `cost_transform`, the cost-to-go is embedded as `50 − Ĉ`, as OSRL's configs do.
//!
//! Tensors are named as OSRL's `CDT.state_dict()` under `cdt.` (`cdt.blocks.0.attention.in_proj_weight`, ...), so a
//! PyTorch model exports by adding the prefix. The prediction heads used only in training (`cost_pred_head`,
//! `state_pred_head`) are accepted and checked when present. Evaluation applies no dropout; training
//! ([`Cdt::training_heads`]) applies OSRL's, with masks from a seeded generator.

use candle_core::{DType, Device, Tensor, Var};

use crate::fused;
use crate::layers::{LayerNorm, Linear, Weights, normal_var};
use crate::noise::Noise;
use crate::{PolicyError, Result};

/// What OSRL subtracts the cost-to-go from when `cost_transform` is on.
pub const COST_TRANSFORM_OFFSET: f64 = 50.0;
/// Tokens per timestep: reward-to-go, cost-to-go, state, action.
const TOKENS: usize = 4;
/// Where the state token sits among them (the action is read from its output).
const STATE_TOKEN: usize = 2;

/// The sizes of a CDT.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CdtShape {
    pub obs_dim: usize,
    pub act_dim: usize,
    pub embedding_dim: usize,
    pub num_layers: usize,
    pub num_heads: usize,
    /// Context length K in timesteps.
    pub seq_len: usize,
    /// Longest episode the timestep embedding covers (it has `episode_len + seq_len` rows).
    pub episode_len: usize,
}

struct Block {
    norm1: LayerNorm,
    norm2: LayerNorm,
    /// `nn.MultiheadAttention`'s packed query/key/value projection: `[3d, d]` and `[3d]`.
    in_proj_weight: Var,
    in_proj_bias: Var,
    out_proj: Linear,
    /// `mlp.0` (d → 4d), GELU, `mlp.2` (4d → d).
    mlp_in: Linear,
    mlp_out: Linear,
}

pub struct Cdt {
    pub shape: CdtShape,
    pub cost_transform: bool,
    timestep_emb: Var,
    state_emb: Linear,
    action_emb: Linear,
    return_emb: Linear,
    cost_emb: Linear,
    emb_norm: LayerNorm,
    blocks: Vec<Block>,
    out_norm: LayerNorm,
    action_mu: Linear,
    action_log_std: Linear,
    cost_pred_head: Option<Linear>,
    state_pred_head: Option<Linear>,
}

/// The names of the tensors only training reads.
pub const TRAINING_ONLY: [&str; 2] = ["cdt.cost_pred_head.", "cdt.state_pred_head."];

impl Cdt {
    fn check(shape: &CdtShape) -> Result<()> {
        let CdtShape {
            embedding_dim: d,
            num_heads: h,
            ..
        } = *shape;
        if d == 0 || h == 0 || d % h != 0 || shape.num_layers == 0 || shape.seq_len == 0 || shape.episode_len == 0 {
            return Err(PolicyError::Format(format!(
                "cdt: embedding_dim ({d}) must be a positive multiple of num_heads ({h}), and num_layers, seq_len \
                 and episode_len positive"
            )));
        }
        // Bounds far above any benchmark model, so that sizes computed from a declaration cannot overflow.
        for (name, value, max) in [
            ("embedding_dim", d, 1 << 14),
            ("num_layers", shape.num_layers, 256),
            ("seq_len", shape.seq_len, 1 << 12),
            ("episode_len", shape.episode_len, 1 << 20),
        ] {
            if value > max {
                return Err(PolicyError::Format(format!(
                    "cdt: {name} = {value} is above the {max} this service reads"
                )));
            }
        }
        Ok(())
    }

    /// A freshly initialised CDT as OSRL builds it: every linear and embedding weight `N(0, 0.02²)`, biases zero,
    /// layer norms one and zero.
    pub fn new(shape: CdtShape, cost_transform: bool, noise: &mut Noise) -> Result<Cdt> {
        Self::check(&shape)?;
        let d = shape.embedding_dim;
        let linear = |i, o, noise: &mut Noise| Linear::normal(i, o, 0.02, noise);
        let mut blocks = Vec::new();
        for _ in 0..shape.num_layers {
            blocks.push(Block {
                norm1: LayerNorm::new(d)?,
                norm2: LayerNorm::new(d)?,
                in_proj_weight: normal_var(&[3 * d, d], 0.02, noise)?,
                in_proj_bias: Var::zeros(3 * d, DType::F32, &Device::Cpu)?,
                out_proj: linear(d, d, noise)?,
                mlp_in: linear(d, 4 * d, noise)?,
                mlp_out: linear(4 * d, d, noise)?,
            });
        }
        Ok(Cdt {
            shape,
            cost_transform,
            timestep_emb: normal_var(&[shape.episode_len + shape.seq_len, d], 0.02, noise)?,
            state_emb: linear(shape.obs_dim, d, noise)?,
            action_emb: linear(shape.act_dim, d, noise)?,
            return_emb: linear(1, d, noise)?,
            cost_emb: linear(1, d, noise)?,
            emb_norm: LayerNorm::new(d)?,
            blocks,
            out_norm: LayerNorm::new(d)?,
            action_mu: linear(d, shape.act_dim, noise)?,
            action_log_std: linear(d, shape.act_dim, noise)?,
            cost_pred_head: Some(linear(d, 2, noise)?),
            state_pred_head: Some(linear(d, shape.obs_dim, noise)?),
        })
    }

    /// Reads a CDT of `shape` from `cdt.`-prefixed tensors, checking every shape.
    pub fn from_weights(shape: CdtShape, cost_transform: bool, w: &mut Weights) -> Result<Cdt> {
        Self::check(&shape)?;
        let d = shape.embedding_dim;
        let mut blocks = Vec::new();
        for i in 0..shape.num_layers {
            let p = format!("cdt.blocks.{i}");
            blocks.push(Block {
                norm1: w.layer_norm(&format!("{p}.norm1"), d)?,
                norm2: w.layer_norm(&format!("{p}.norm2"), d)?,
                in_proj_weight: w.var(&format!("{p}.attention.in_proj_weight"), &[3 * d, d])?,
                in_proj_bias: w.var(&format!("{p}.attention.in_proj_bias"), &[3 * d])?,
                out_proj: w.linear(&format!("{p}.attention.out_proj"), d, d)?,
                mlp_in: w.linear(&format!("{p}.mlp.0"), d, 4 * d)?,
                mlp_out: w.linear(&format!("{p}.mlp.2"), 4 * d, d)?,
            });
        }
        Ok(Cdt {
            shape,
            cost_transform,
            timestep_emb: w.var("cdt.timestep_emb.weight", &[shape.episode_len + shape.seq_len, d])?,
            state_emb: w.linear("cdt.state_emb", shape.obs_dim, d)?,
            action_emb: w.linear("cdt.action_emb", shape.act_dim, d)?,
            return_emb: w.linear("cdt.return_emb", 1, d)?,
            cost_emb: w.linear("cdt.cost_emb", 1, d)?,
            emb_norm: w.layer_norm("cdt.emb_norm", d)?,
            blocks,
            out_norm: w.layer_norm("cdt.out_norm", d)?,
            action_mu: w.linear("cdt.action_head.mu", d, shape.act_dim)?,
            action_log_std: w.linear("cdt.action_head.log_std", d, shape.act_dim)?,
            cost_pred_head: w.optional_linear("cdt.cost_pred_head", d, 2)?,
            state_pred_head: w.optional_linear("cdt.state_pred_head", d, shape.obs_dim)?,
        })
    }

    pub fn named_vars(&self) -> Vec<(String, Var)> {
        let mut out = vec![("cdt.timestep_emb.weight".to_owned(), self.timestep_emb.clone())];
        for (name, linear) in [
            ("cdt.state_emb", &self.state_emb),
            ("cdt.action_emb", &self.action_emb),
            ("cdt.return_emb", &self.return_emb),
            ("cdt.cost_emb", &self.cost_emb),
            ("cdt.action_head.mu", &self.action_mu),
            ("cdt.action_head.log_std", &self.action_log_std),
        ] {
            out.extend(linear.named_vars(name));
        }
        for (name, head) in [
            ("cdt.cost_pred_head", &self.cost_pred_head),
            ("cdt.state_pred_head", &self.state_pred_head),
        ] {
            if let Some(head) = head {
                out.extend(head.named_vars(name));
            }
        }
        out.extend(self.emb_norm.named_vars("cdt.emb_norm"));
        out.extend(self.out_norm.named_vars("cdt.out_norm"));
        for (i, b) in self.blocks.iter().enumerate() {
            let p = format!("cdt.blocks.{i}");
            out.extend(b.norm1.named_vars(&format!("{p}.norm1")));
            out.extend(b.norm2.named_vars(&format!("{p}.norm2")));
            out.push((format!("{p}.attention.in_proj_weight"), b.in_proj_weight.clone()));
            out.push((format!("{p}.attention.in_proj_bias"), b.in_proj_bias.clone()));
            out.extend(b.out_proj.named_vars(&format!("{p}.attention.out_proj")));
            out.extend(b.mlp_in.named_vars(&format!("{p}.mlp.0")));
            out.extend(b.mlp_out.named_vars(&format!("{p}.mlp.2")));
        }
        out
    }

    /// The action head's mean at every timestep: `states [B, T, obs]`, `actions [B, T, act]`, `returns_to_go` and
    /// `costs_to_go [B, T]`, `timesteps [B, T]` (u32) → `[B, T, act]`.
    ///
    /// Attention is causal, so the output at timestep `t` depends on timesteps `≤ t` only: sequences of different
    /// lengths can share a batch padded at the end, each read at its own last timestep.
    pub fn action_means(
        &self,
        states: &Tensor,
        actions: &Tensor,
        returns_to_go: &Tensor,
        costs_to_go: &Tensor,
        timesteps: &Tensor,
    ) -> Result<Tensor> {
        let x = self.encode(states, actions, returns_to_go, costs_to_go, timesteps, None)?;
        self.action_mu.forward(&x.narrow(2, STATE_TOKEN, 1)?.squeeze(2)?)
    }

    /// What training reads, with dropout drawn from `training`: the action head's mean and log σ at every
    /// state token (`[B, T, act]` each) and the cost head's logits at every action token (`[B, T, 2]`).
    ///
    /// OSRL also masks padded keys; padding sits at the end of each window and attention is causal, so no valid
    /// position ever attends to a padded one and the losses (over valid positions) are the same without it.
    pub fn training_heads(
        &self,
        states: &Tensor,
        actions: &Tensor,
        returns_to_go: &Tensor,
        costs_to_go: &Tensor,
        timesteps: &Tensor,
        training: &mut Training,
    ) -> Result<(Tensor, Tensor, Tensor)> {
        let x = self.encode(states, actions, returns_to_go, costs_to_go, timesteps, Some(training))?;
        let state_out = x.narrow(2, STATE_TOKEN, 1)?.squeeze(2)?;
        let action_out = x.narrow(2, STATE_TOKEN + 1, 1)?.squeeze(2)?;
        let cost_head = self
            .cost_pred_head
            .as_ref()
            .ok_or_else(|| PolicyError::Format("cdt: training needs the cost prediction head".into()))?;
        Ok((
            self.action_mu.forward(&state_out)?,
            self.action_log_std.forward(&state_out)?,
            cost_head.forward(&action_out)?,
        ))
    }

    /// The token sequence through the transformer: `[B, T, 4, d]` after the final layer norm.
    fn encode(
        &self,
        states: &Tensor,
        actions: &Tensor,
        returns_to_go: &Tensor,
        costs_to_go: &Tensor,
        timesteps: &Tensor,
        mut training: Option<&mut Training>,
    ) -> Result<Tensor> {
        let (b, t, _) = states.dims3()?;
        let d = self.shape.embedding_dim;
        let time = self
            .timestep_emb
            .as_tensor()
            .index_select(&timesteps.flatten_all()?, 0)?
            .reshape((b, t, d))?;
        let costs_to_go = if self.cost_transform {
            costs_to_go.affine(-1.0, COST_TRANSFORM_OFFSET)?
        } else {
            costs_to_go.clone()
        };
        let tokens = [
            self.return_emb.forward(&returns_to_go.unsqueeze(2)?)?,
            self.cost_emb.forward(&costs_to_go.unsqueeze(2)?)?,
            self.state_emb.forward(states)?,
            self.action_emb.forward(actions)?,
        ]
        .iter()
        .map(|x| x.add(&time))
        .collect::<candle_core::Result<Vec<_>>>()?;
        // [B, T, 4, d] → [B, 4T, d]: R̂_0, Ĉ_0, s_0, a_0, R̂_1, ...
        let mut x = Tensor::stack(&tokens, 2)?.reshape((b, TOKENS * t, d))?;
        x = self.emb_norm.forward(&x)?;
        if let Some(training) = training.as_deref_mut() {
            x = training.dropout(&x)?;
        }
        for block in &self.blocks {
            x = block.forward(&x, self.shape.num_heads, training.as_deref_mut())?;
        }
        x = self.out_norm.forward(&x)?;
        Ok(x.reshape((b, t, TOKENS, d))?)
    }

    /// The action head's log standard deviations (training's likelihood; unused when evaluating at the mean).
    pub fn action_log_std(&self, features: &Tensor) -> Result<Tensor> {
        self.action_log_std.forward(features)
    }

    /// The network on `device` (training builds it on the CPU from its seed, then moves it).
    pub fn to_device(&self, device: &Device) -> Result<Cdt> {
        let linear = |l: &Linear| l.to_device(device);
        let optional = |l: &Option<Linear>| l.as_ref().map(linear).transpose();
        Ok(Cdt {
            shape: self.shape,
            cost_transform: self.cost_transform,
            timestep_emb: crate::var_on(&self.timestep_emb, device)?,
            state_emb: linear(&self.state_emb)?,
            action_emb: linear(&self.action_emb)?,
            return_emb: linear(&self.return_emb)?,
            cost_emb: linear(&self.cost_emb)?,
            emb_norm: self.emb_norm.to_device(device)?,
            blocks: self
                .blocks
                .iter()
                .map(|b| {
                    Ok(Block {
                        norm1: b.norm1.to_device(device)?,
                        norm2: b.norm2.to_device(device)?,
                        in_proj_weight: crate::var_on(&b.in_proj_weight, device)?,
                        in_proj_bias: crate::var_on(&b.in_proj_bias, device)?,
                        out_proj: linear(&b.out_proj)?,
                        mlp_in: linear(&b.mlp_in)?,
                        mlp_out: linear(&b.mlp_out)?,
                    })
                })
                .collect::<Result<_>>()?,
            out_norm: self.out_norm.to_device(device)?,
            action_mu: linear(&self.action_mu)?,
            action_log_std: linear(&self.action_log_std)?,
            cost_pred_head: optional(&self.cost_pred_head)?,
            state_pred_head: optional(&self.state_pred_head)?,
        })
    }
}

impl Block {
    /// Pre-LN: `x + Dropout(Attention(LN(x)))`, then `x + Dropout(MLP(LN(x)))`; attention weights drop out too
    /// when training (PyTorch's `nn.MultiheadAttention` dropout).
    fn forward(&self, x: &Tensor, heads: usize, mut training: Option<&mut Training>) -> Result<Tensor> {
        let (b, l, d) = x.dims3()?;
        let head_dim = d / heads;
        let h = self.norm1.forward(x)?;
        // Query, key and value each from their rows of the packed projection, `[B, heads, L, head_dim]`. Slicing
        // the weights rather than one packed output keeps the slices' gradients weight-sized.
        let rows = h.reshape((b * l, d))?;
        let project = |i: usize| -> Result<Tensor> {
            let weight = self.in_proj_weight.as_tensor().narrow(0, i * d, d)?;
            let bias = self.in_proj_bias.as_tensor().narrow(0, i * d, d)?;
            Ok(fused::bias_add(&rows.matmul(&weight.t()?)?, &bias)?
                .reshape((b, l, heads, head_dim))?
                .transpose(1, 2)?
                .contiguous()?)
        };
        let (q, k, v) = (project(0)?, project(1)?, project(2)?);
        let scores = q
            .affine(1.0 / (head_dim as f64).sqrt(), 0.0)?
            .matmul(&k.transpose(2, 3)?.contiguous()?)?;
        // Causal: each token attends to itself and the tokens before it.
        let mut weights = fused::causal_softmax(&scores)?;
        if let Some(training) = training.as_deref_mut() {
            weights = training.dropout(&weights)?;
        }
        let attended = weights.matmul(&v)?.transpose(1, 2)?.contiguous()?.reshape((b, l, d))?;
        let mut attention_out = self.out_proj.forward(&attended)?;
        if let Some(training) = training.as_deref_mut() {
            attention_out = training.dropout(&attention_out)?;
        }
        let x = x.add(&attention_out)?;
        let hidden = fused::gelu_erf(&self.mlp_in.forward(&self.norm2.forward(&x)?)?)?;
        let mut mlp_out = self.mlp_out.forward(&hidden)?;
        if let Some(training) = training {
            mlp_out = training.dropout(&mlp_out)?;
        }
        Ok(x.add(&mlp_out)?)
    }
}

/// Training mode: dropout with probability `p` (OSRL: 0.1 everywhere), its masks drawn from a seeded generator so
/// that a training run is reproducible.
pub struct Training<'a> {
    pub p: f64,
    pub noise: &'a mut Noise,
}

impl Training<'_> {
    /// Zeroes each element with probability `p` and scales the rest by `1/(1 − p)`, as `nn.Dropout` in training
    /// (the mask from [`Noise::dropout_keep`]).
    pub fn dropout(&mut self, x: &Tensor) -> Result<Tensor> {
        if self.p <= 0.0 {
            return Ok(x.clone());
        }
        let keep = self.noise.dropout_keep(x.elem_count(), self.p);
        Ok(fused::dropout(x, keep, self.p)?)
    }
}

/// What one environment's CDT has seen this episode: the model's inputs at every timestep so far.
#[derive(Debug, Clone, Default)]
pub struct CdtContext {
    states: Vec<f32>,
    actions: Vec<f32>,
    returns_to_go: Vec<f32>,
    costs_to_go: Vec<f32>,
}

impl CdtContext {
    /// A new episode conditioned on `(R̂_0, Ĉ_0)` (already scaled).
    pub fn new(return_to_go: f32, cost_to_go: f32) -> CdtContext {
        CdtContext {
            returns_to_go: vec![return_to_go],
            costs_to_go: vec![cost_to_go],
            ..CdtContext::default()
        }
    }

    /// Timesteps seen (observations received).
    fn steps(&self, obs_dim: usize) -> usize {
        self.states.len() / obs_dim.max(1)
    }

    /// After a step: the reward- and cost-to-go of the next timestep, `R̂ − r`, `Ĉ − c` (already scaled), in float32
    /// as OSRL's rollout tensors hold them.
    pub fn record(&mut self, scaled_reward: f32, scaled_cost: f32) {
        let (r, c) = (
            *self.returns_to_go.last().unwrap_or(&0.0),
            *self.costs_to_go.last().unwrap_or(&0.0),
        );
        self.returns_to_go.push(r - scaled_reward);
        self.costs_to_go.push(c - scaled_cost);
    }
}

impl Cdt {
    /// Actions for several environments at once: each context receives its new observation, the model reads its
    /// last `seq_len` timesteps (the current action slot zero, as OSRL's rollout feeds it), and the mean of the
    /// action head at the current timestep, clamped to `±max_action`, is recorded and returned (row-major).
    pub fn act(&self, contexts: &mut [&mut CdtContext], observations: &[f32], max_action: f64) -> Result<Vec<f32>> {
        let CdtShape {
            obs_dim,
            act_dim,
            seq_len,
            episode_len,
            ..
        } = self.shape;
        let n = contexts.len();
        if n == 0 {
            return Ok(Vec::new());
        }
        for (i, c) in contexts.iter_mut().enumerate() {
            if c.steps(obs_dim) >= episode_len {
                return Err(PolicyError::Format(format!(
                    "cdt: an episode went past the {episode_len} steps its timestep embedding covers"
                )));
            }
            c.states
                .extend_from_slice(&observations[i * obs_dim..(i + 1) * obs_dim]);
            c.actions.extend(std::iter::repeat_n(0.0, act_dim));
        }
        // The window of each context: its last `seq_len` timesteps, padded at the end to the longest window.
        let windows: Vec<(usize, usize)> = contexts
            .iter()
            .map(|c| {
                let steps = c.steps(obs_dim);
                let len = steps.min(seq_len);
                (steps - len, len)
            })
            .collect();
        let t = windows.iter().map(|w| w.1).max().unwrap_or(1);
        let (mut s, mut a) = (vec![0f32; n * t * obs_dim], vec![0f32; n * t * act_dim]);
        let (mut r, mut c, mut ts) = (vec![0f32; n * t], vec![0f32; n * t], vec![0u32; n * t]);
        for (i, (ctx, &(start, len))) in contexts.iter().zip(&windows).enumerate() {
            let row = i * t;
            s[row * obs_dim..(row + len) * obs_dim]
                .copy_from_slice(&ctx.states[start * obs_dim..(start + len) * obs_dim]);
            a[row * act_dim..(row + len) * act_dim]
                .copy_from_slice(&ctx.actions[start * act_dim..(start + len) * act_dim]);
            r[row..row + len].copy_from_slice(&ctx.returns_to_go[start..start + len]);
            c[row..row + len].copy_from_slice(&ctx.costs_to_go[start..start + len]);
            for (k, step) in (start..start + len).enumerate() {
                ts[row + k] = step as u32;
            }
        }
        let cpu = &Device::Cpu;
        let means = self.action_means(
            &Tensor::from_vec(s, (n, t, obs_dim), cpu)?,
            &Tensor::from_vec(a, (n, t, act_dim), cpu)?,
            &Tensor::from_vec(r, (n, t), cpu)?,
            &Tensor::from_vec(c, (n, t), cpu)?,
            &Tensor::from_vec(ts, (n, t), cpu)?,
        )?;
        // NaN kept (see `fused::clamp`): the evaluator refuses a non-finite action.
        let means = crate::fused::clamp(&means, -max_action, max_action)?.to_vec3::<f32>()?;
        let mut out = Vec::with_capacity(n * act_dim);
        for (ctx, ((_, len), rows)) in contexts.iter_mut().zip(windows.iter().zip(means)) {
            let action = &rows[len - 1];
            let at = ctx.actions.len() - act_dim;
            ctx.actions[at..].copy_from_slice(action);
            out.extend_from_slice(action);
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dropout_drops_where_the_uniform_draw_is_below_p() {
        let x = Tensor::ones((4, 250), DType::F32, &Device::Cpu).unwrap();
        for p in [0.1, 0.25, 0.5] {
            let mut noise = Noise::seeded(21);
            let out: Vec<f32> = Training { p, noise: &mut noise }
                .dropout(&x)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let mut replay = Noise::seeded(21);
            let keep = (1.0 / (1.0 - p)) as f32;
            for (i, got) in out.iter().enumerate() {
                let want = if replay.uniform() < p { 0.0 } else { keep };
                assert_eq!(*got, want, "p {p}, element {i}");
            }
            let dropped = out.iter().filter(|v| **v == 0.0).count() as f64 / out.len() as f64;
            assert!((dropped - p).abs() < 0.06, "p {p}: dropped {dropped}");
        }
    }

    #[test]
    fn training_gradients_through_attention_layer_norm_and_gelu_match_finite_differences() {
        let cdt = Cdt::new(shape(), true, &mut Noise::seeded(3)).unwrap();
        let mut noise = Noise::seeded(4);
        let cpu = &Device::Cpu;
        let (b, t) = (2, 3);
        let states = Tensor::from_vec(noise.normals_f32(b * t * 3), (b, t, 3), cpu).unwrap();
        let actions = Tensor::from_vec(noise.normals_f32(b * t * 2), (b, t, 2), cpu).unwrap();
        let rtg = Tensor::from_vec(noise.normals_f32(b * t), (b, t), cpu).unwrap();
        let ctg = Tensor::from_vec(noise.normals_f32(b * t), (b, t), cpu).unwrap();
        let steps = Tensor::from_vec(vec![0u32, 1, 2, 5, 6, 7], (b, t), cpu).unwrap();
        let weights = Tensor::from_vec(noise.normals_f32(b * t * 2), (b, t, 2), cpu).unwrap();
        // A scalar reading all three heads; dropout 0 so that it is a plain function of the weights.
        let loss = || {
            let mut quiet = Noise::seeded(0);
            let mut training = Training {
                p: 0.0,
                noise: &mut quiet,
            };
            let (mu, log_std, cost) = cdt
                .training_heads(&states, &actions, &rtg, &ctg, &steps, &mut training)
                .unwrap();
            mu.mul(&weights)
                .unwrap()
                .sum_all()
                .unwrap()
                .add(&log_std.sqr().unwrap().sum_all().unwrap())
                .unwrap()
                .add(&cost.tanh().unwrap().sum_all().unwrap())
                .unwrap()
        };
        let grads = loss().backward().unwrap();
        // The packed attention projection (softmax, scaling), the MLP's first layer (GELU) and a layer norm's gain.
        for (var, picks) in [
            (&cdt.blocks[0].in_proj_weight, [0usize, 17, 300]),
            (&cdt.blocks[1].mlp_in.weight, [3, 40, 200]),
            (&cdt.blocks[0].norm1.weight, [0, 5, 11]),
        ] {
            let analytic: Vec<f32> = grads
                .get(var.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let base: Vec<f32> = var.as_tensor().flatten_all().unwrap().to_vec1().unwrap();
            let h = 1e-2f32;
            for k in picks {
                let at = |d: f32| {
                    let mut v = base.clone();
                    v[k] += d;
                    var.set(&Tensor::from_vec(v, var.as_tensor().dims(), cpu).unwrap())
                        .unwrap();
                    loss().to_scalar::<f32>().unwrap()
                };
                let numeric = (at(h) - at(-h)) / (2.0 * h);
                var.set(&Tensor::from_vec(base.clone(), var.as_tensor().dims(), cpu).unwrap())
                    .unwrap();
                assert!(
                    (numeric - analytic[k]).abs() < 2e-2 * (1.0 + analytic[k].abs()),
                    "{k}: {numeric} vs {}",
                    analytic[k]
                );
            }
        }
    }

    fn shape() -> CdtShape {
        CdtShape {
            obs_dim: 3,
            act_dim: 2,
            embedding_dim: 16,
            num_layers: 2,
            num_heads: 4,
            seq_len: 4,
            episode_len: 20,
        }
    }

    #[test]
    fn batched_padded_contexts_act_as_each_context_alone() {
        let cdt = Cdt::new(shape(), true, &mut Noise::seeded(9)).unwrap();
        let mut noise = Noise::seeded(10);
        // Two environments out of step: the second starts three steps later, and both run past the window.
        let (mut a, mut b) = (CdtContext::new(30.0, 10.0), CdtContext::new(20.0, 5.0));
        let (mut a_alone, mut b_alone) = (a.clone(), b.clone());
        for step in 0..8 {
            let obs: Vec<f32> = (0..6).map(|_| noise.normal() as f32).collect();
            if step < 3 {
                let alone = cdt.act(&mut [&mut a_alone], &obs[..3], 1.0).unwrap();
                let batched = cdt.act(&mut [&mut a], &obs[..3], 1.0).unwrap();
                assert_eq!(alone, batched);
            } else {
                let batched = cdt.act(&mut [&mut a, &mut b], &obs, 1.0).unwrap();
                let first = cdt.act(&mut [&mut a_alone], &obs[..3], 1.0).unwrap();
                let second = cdt.act(&mut [&mut b_alone], &obs[3..], 1.0).unwrap();
                for (x, y) in batched.iter().zip(first.iter().chain(&second)) {
                    assert!((x - y).abs() < 1e-5, "step {step}: {batched:?} vs {first:?} {second:?}");
                }
                b.record(0.5, 1.0);
                b_alone.record(0.5, 1.0);
            }
            a.record(0.25, 0.0);
            a_alone.record(0.25, 0.0);
        }
        assert_eq!(a.returns_to_go.len(), 9);
        assert_eq!(a.returns_to_go[8], 30.0 - 8.0 * 0.25);
    }

    #[test]
    fn the_action_depends_on_the_targets_and_reads_back_from_named_tensors() {
        let cdt = Cdt::new(shape(), true, &mut Noise::seeded(1)).unwrap();
        let obs = [0.1f32, -0.4, 0.7];
        let act = |cdt: &Cdt, r: f32, c: f32| cdt.act(&mut [&mut CdtContext::new(r, c)], &obs, 1.0).unwrap();
        assert_ne!(act(&cdt, 30.0, 10.0), act(&cdt, 30.0, 40.0));
        assert_ne!(act(&cdt, 30.0, 10.0), act(&cdt, 60.0, 10.0));
        let tensors: std::collections::HashMap<String, Tensor> =
            crate::tensors_of(cdt.named_vars()).into_iter().collect();
        let mut weights = Weights::new(&tensors);
        let back = Cdt::from_weights(shape(), true, &mut weights).unwrap();
        weights.finish(&TRAINING_ONLY).unwrap();
        assert_eq!(act(&back, 30.0, 10.0), act(&cdt, 30.0, 10.0));
        // A declared shape the weights do not have is refused with the tensor's name.
        let wrong = CdtShape {
            episode_len: 30,
            ..shape()
        };
        let err = Cdt::from_weights(wrong, true, &mut Weights::new(&tensors))
            .err()
            .unwrap()
            .to_string();
        assert!(
            err.contains("cdt.timestep_emb.weight has shape [24, 16], expected [34, 16]"),
            "{err}"
        );
        // A context past the episode length is an error, not an out-of-range embedding lookup.
        let mut ctx = CdtContext::new(1.0, 1.0);
        for _ in 0..20 {
            cdt.act(&mut [&mut ctx], &obs, 1.0).unwrap();
            ctx.record(0.0, 0.0);
        }
        assert!(cdt.act(&mut [&mut ctx], &obs, 1.0).is_err());
    }

    #[test]
    fn attention_is_causal() {
        // Changing a later timestep's inputs leaves an earlier timestep's output unchanged.
        let cdt = Cdt::new(shape(), false, &mut Noise::seeded(2)).unwrap();
        let mut noise = Noise::seeded(3);
        let rand = |n: usize, noise: &mut Noise| (0..n).map(|_| noise.normal() as f32).collect::<Vec<_>>();
        let cpu = &Device::Cpu;
        let (s, a, r, c) = (
            rand(12, &mut noise),
            rand(8, &mut noise),
            rand(4, &mut noise),
            rand(4, &mut noise),
        );
        let run = |s: &[f32]| {
            cdt.action_means(
                &Tensor::from_slice(s, (1, 4, 3), cpu).unwrap(),
                &Tensor::from_slice(&a, (1, 4, 2), cpu).unwrap(),
                &Tensor::from_slice(&r, (1, 4), cpu).unwrap(),
                &Tensor::from_slice(&c, (1, 4), cpu).unwrap(),
                &Tensor::from_slice(&[0u32, 1, 2, 3], (1, 4), cpu).unwrap(),
            )
            .unwrap()
            .to_vec3::<f32>()
            .unwrap()
        };
        let mut changed = s.clone();
        changed[9] += 1.0;
        let (x, y) = (run(&s), run(&changed));
        assert_eq!(x[0][..3], y[0][..3]);
        assert_ne!(x[0][3], y[0][3]);
    }
}
