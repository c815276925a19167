//! FISOR's actor (Zheng et al., ICLR 2024; its code's `jaxrl5/networks/{diffusion,resnet}.py`): a diffusion model
//! that predicts the noise in a noised action, sampled by DDPM over several candidate actions per state, of which a
//! critic picks one. It acts in several network passes per step, all declared in `policy.json` (the `diffusion`
//! architecture and its `sampler`):
//!
//! ```text
//! ε̂(s, x, t) = output(mish(blocks(input([x, s, cond(fourier(t))]))))
//! fourier(t) = [cos 2π·t·Wᵀ, sin 2π·t·Wᵀ]           W learnable, [time_dim / 2, 1]; t the step index 0..T
//! cond       = Linear → mish → Linear               (the conditioning MLP)
//! block(x)   = x + project(mish(expand(LayerNorm(dropout(x)))))      expand: h → 4h, project: 4h → h
//!
//! x_T ~ N(0, I)                                     one row per candidate, N candidates per state
//! x_{t−1} = clip((x_t − (1−α_t)/√(1−ᾱ_t)·ε̂(s, x_t, t)) / √α_t + [t > 0]·√β_t·temperature·z, −1, 1)
//! action  = max_action · the candidate the critic ranks best (FISOR: lowest max over its feasibility critics)
//! ```
//!
//! with the discrete VP schedule `α_t = exp(−b_min/T − ½(b_max − b_min)(2t − 1)/T²)` for `t = 1..T`, `β = 1 − α`,
//! `ᾱ = cumprod(α)`. The evaluator draws every candidate's noise from a generator seeded with the episode's seed,
//! one per environment slot, so an action depends on the episode seed and the steps so far, never on the batching.

use candle_core::{DType, Device, Tensor, Var};

use crate::Result;
pub use crate::checkpoint::CandidateChoice;
use crate::layers::{LayerNorm, Linear, Weights};
use crate::mlp::{Activation, Mlp, layer_sizes};
use crate::noise::Noise;
use crate::offline::{Ensemble, repeat_rows, softplus};

/// The sizes of a noise-prediction network.
#[derive(Debug, Clone, PartialEq)]
pub struct DiffusionShape {
    pub obs_dim: usize,
    pub act_dim: usize,
    /// Fourier features of the step index (even: half cosines, half sines).
    pub time_dim: usize,
    /// The conditioning MLP's layers after the features (FISOR: [128, 128]); the last is the conditioning's width.
    pub cond_sizes: Vec<usize>,
    pub hidden_dim: usize,
    pub num_blocks: usize,
    pub layer_norm: bool,
}

impl DiffusionShape {
    fn cond_dim(&self) -> usize {
        self.cond_sizes.last().copied().unwrap_or(self.time_dim)
    }
}

/// `x · tanh(softplus(x))`.
pub fn mish(x: &Tensor) -> Result<Tensor> {
    Ok(x.mul(&softplus(x)?.tanh()?)?)
}

/// Flax's `Dropout` while training: each entry kept with probability `1 − rate` and scaled by `1/(1 − rate)` (the
/// CDT's dropout: the mask from [`Noise::dropout_keep`], one fused operation).
fn dropout(x: &Tensor, rate: f64, noise: &mut Noise) -> Result<Tensor> {
    if rate <= 0.0 {
        return Ok(x.clone());
    }
    Ok(crate::fused::dropout(
        x,
        noise.dropout_keep(x.elem_count(), rate),
        rate,
    )?)
}

/// A linear layer `fan_in → fan_out` with zero bias and weights from `draw(fan_in, fan_out)`.
fn linear_from(fan_in: usize, fan_out: usize, weights: Vec<f32>) -> Result<Linear> {
    Ok(Linear {
        weight: Var::from_vec(weights, (fan_out, fan_in), &Device::Cpu)?,
        bias: Var::zeros(fan_out, DType::F32, &Device::Cpu)?,
    })
}

/// Flax's `xavier_uniform`: uniform in ±√(6 / (fan_in + fan_out)).
pub fn xavier_linear(fan_in: usize, fan_out: usize, noise: &mut Noise) -> Result<Linear> {
    let bound = (6.0 / (fan_in + fan_out) as f64).sqrt();
    let w = (0..fan_in * fan_out)
        .map(|_| ((noise.uniform() * 2.0 - 1.0) * bound) as f32)
        .collect();
    linear_from(fan_in, fan_out, w)
}

/// Flax's default `lecun_normal`: a normal truncated at ±2σ, rescaled so its standard deviation is `1/√fan_in`.
fn lecun_linear(fan_in: usize, fan_out: usize, noise: &mut Noise) -> Result<Linear> {
    // The standard deviation of N(0, 1) truncated to ±2.
    const TRUNCATED_STD: f64 = 0.879_625_661_034_239_8;
    let std = (1.0 / fan_in as f64).sqrt() / TRUNCATED_STD;
    let w = (0..fan_in * fan_out)
        .map(|_| {
            loop {
                let z = noise.normal();
                if z.abs() < 2.0 {
                    break (z * std) as f32;
                }
            }
        })
        .collect();
    linear_from(fan_in, fan_out, w)
}

struct Block {
    norm: Option<LayerNorm>,
    expand: Linear,
    project: Linear,
}

/// The noise-prediction network `ε̂(s, x, t)`, tensors `<prefix>.time.kernel`, `<prefix>.cond.<i>`,
/// `<prefix>.input`, `<prefix>.blocks.<k>.{norm,expand,project}`, `<prefix>.output`.
pub struct NoiseNet {
    pub shape: DiffusionShape,
    time_kernel: Var,
    cond: Vec<Linear>,
    input: Linear,
    blocks: Vec<Block>,
    output: Linear,
}

impl NoiseNet {
    /// FISOR's initialisation: the time kernel `N(0, 0.2²)`, the conditioning, input and output layers
    /// xavier-uniform, the blocks' layers lecun-normal; zero biases, LayerNorm weight one.
    pub fn new(shape: DiffusionShape, noise: &mut Noise) -> Result<NoiseNet> {
        check_shape(&shape)?;
        let time_kernel = crate::layers::normal_var(&[shape.time_dim / 2, 1], 0.2, noise)?;
        let mut cond = Vec::new();
        let mut width = shape.time_dim;
        for &size in &shape.cond_sizes {
            cond.push(xavier_linear(width, size, noise)?);
            width = size;
        }
        let h = shape.hidden_dim;
        let input = xavier_linear(shape.act_dim + shape.obs_dim + shape.cond_dim(), h, noise)?;
        let blocks = (0..shape.num_blocks)
            .map(|_| {
                Ok(Block {
                    norm: if shape.layer_norm {
                        Some(LayerNorm::new(h)?)
                    } else {
                        None
                    },
                    expand: lecun_linear(h, 4 * h, noise)?,
                    project: lecun_linear(4 * h, h, noise)?,
                })
            })
            .collect::<Result<_>>()?;
        let output = xavier_linear(h, shape.act_dim, noise)?;
        Ok(NoiseNet {
            shape,
            time_kernel,
            cond,
            input,
            blocks,
            output,
        })
    }

    /// The declared network read out of a checkpoint under `prefix`, every shape checked.
    pub fn from_weights(shape: DiffusionShape, prefix: &str, w: &mut Weights) -> Result<NoiseNet> {
        check_shape(&shape)?;
        let time_kernel = w.var(&format!("{prefix}.time.kernel"), &[shape.time_dim / 2, 1])?;
        let mut cond = Vec::new();
        let mut width = shape.time_dim;
        for (i, &size) in shape.cond_sizes.iter().enumerate() {
            cond.push(w.linear(&format!("{prefix}.cond.{i}"), width, size)?);
            width = size;
        }
        let h = shape.hidden_dim;
        let input = w.linear(
            &format!("{prefix}.input"),
            shape.act_dim + shape.obs_dim + shape.cond_dim(),
            h,
        )?;
        let blocks = (0..shape.num_blocks)
            .map(|k| {
                let at = format!("{prefix}.blocks.{k}");
                Ok(Block {
                    norm: if shape.layer_norm {
                        Some(w.layer_norm(&format!("{at}.norm"), h)?)
                    } else {
                        None
                    },
                    expand: w.linear(&format!("{at}.expand"), h, 4 * h)?,
                    project: w.linear(&format!("{at}.project"), 4 * h, h)?,
                })
            })
            .collect::<Result<_>>()?;
        let output = w.linear(&format!("{prefix}.output"), h, shape.act_dim)?;
        Ok(NoiseNet {
            shape,
            time_kernel,
            cond,
            input,
            blocks,
            output,
        })
    }

    /// `ε̂` for rows of observations `[R, obs]`, noised actions `[R, act]` and step indices `[R, 1]`; `dropout` is
    /// the training rate and its generator (none at evaluation).
    pub fn forward(&self, obs: &Tensor, x: &Tensor, t: &Tensor, dropout: Option<(f64, &mut Noise)>) -> Result<Tensor> {
        let f = t
            .matmul(&self.time_kernel.as_tensor().t()?)?
            .affine(std::f64::consts::TAU, 0.0)?;
        let mut cond = Tensor::cat(&[f.cos()?, f.sin()?], 1)?;
        for (i, layer) in self.cond.iter().enumerate() {
            cond = layer.forward(&cond)?;
            if i + 1 < self.cond.len() {
                cond = mish(&cond)?;
            }
        }
        let mut h = self.input.forward(&Tensor::cat(&[x, obs, &cond], 1)?)?;
        let mut dropout = dropout;
        for block in &self.blocks {
            let mut y = match dropout.as_mut() {
                Some((rate, noise)) => self::dropout(&h, *rate, noise)?,
                None => h.clone(),
            };
            if let Some(norm) = &block.norm {
                y = norm.forward(&y)?;
            }
            y = block.project.forward(&mish(&block.expand.forward(&y)?)?)?;
            h = h.add(&y)?;
        }
        self.output.forward(&mish(&h)?)
    }

    pub fn named_vars(&self, prefix: &str) -> Vec<(String, Var)> {
        let mut out = vec![(format!("{prefix}.time.kernel"), self.time_kernel.clone())];
        for (i, layer) in self.cond.iter().enumerate() {
            out.extend(layer.named_vars(&format!("{prefix}.cond.{i}")));
        }
        out.extend(self.input.named_vars(&format!("{prefix}.input")));
        for (k, block) in self.blocks.iter().enumerate() {
            let at = format!("{prefix}.blocks.{k}");
            if let Some(norm) = &block.norm {
                out.extend(norm.named_vars(&format!("{at}.norm")));
            }
            out.extend(block.expand.named_vars(&format!("{at}.expand")));
            out.extend(block.project.named_vars(&format!("{at}.project")));
        }
        out.extend(self.output.named_vars(&format!("{prefix}.output")));
        out
    }

    /// The same network on `device`.
    pub fn to_device(&self, device: &Device) -> Result<NoiseNet> {
        Ok(NoiseNet {
            shape: self.shape.clone(),
            time_kernel: crate::var_on(&self.time_kernel, device)?,
            cond: self.cond.iter().map(|l| l.to_device(device)).collect::<Result<_>>()?,
            input: self.input.to_device(device)?,
            blocks: self
                .blocks
                .iter()
                .map(|b| {
                    Ok(Block {
                        norm: b.norm.as_ref().map(|n| n.to_device(device)).transpose()?,
                        expand: b.expand.to_device(device)?,
                        project: b.project.to_device(device)?,
                    })
                })
                .collect::<Result<_>>()?,
            output: self.output.to_device(device)?,
        })
    }

    /// A copy whose variables are its own (the EMA actor starts as one).
    pub fn copy(&self) -> Result<NoiseNet> {
        let tensors: std::collections::HashMap<String, Tensor> =
            crate::tensors_of(self.named_vars("net")).into_iter().collect();
        NoiseNet::from_weights(self.shape.clone(), "net", &mut Weights::new(&tensors))
    }
}

fn check_shape(shape: &DiffusionShape) -> Result<()> {
    let ok = shape.time_dim >= 2
        && shape.time_dim.is_multiple_of(2)
        && shape.hidden_dim > 0
        && !shape.cond_sizes.contains(&0)
        && shape.num_blocks <= 64;
    if ok {
        Ok(())
    } else {
        Err(crate::PolicyError::Format(
            "diffusion: time_dim must be even and positive, hidden_dim and cond_sizes positive, num_blocks at most 64"
                .into(),
        ))
    }
}

/// The discrete VP schedule over `steps` denoising steps.
#[derive(Debug, Clone, PartialEq)]
pub struct Schedule {
    pub alphas: Vec<f64>,
    pub alpha_hats: Vec<f64>,
    pub betas: Vec<f64>,
}

impl Schedule {
    /// `α_t = exp(−b_min/T − ½(b_max − b_min)(2t − 1)/T²)`, `t = 1..T` (index `t − 1`).
    pub fn vp(steps: usize, beta_min: f64, beta_max: f64) -> Schedule {
        let t_max = steps as f64;
        let alphas: Vec<f64> = (1..=steps)
            .map(|t| (-beta_min / t_max - 0.5 * (beta_max - beta_min) * (2.0 * t as f64 - 1.0) / (t_max * t_max)).exp())
            .collect();
        let alpha_hats = alphas
            .iter()
            .scan(1.0, |acc, a| {
                *acc *= a;
                Some(*acc)
            })
            .collect();
        let betas = alphas.iter().map(|a| 1.0 - a).collect();
        Schedule {
            alphas,
            alpha_hats,
            betas,
        }
    }

    pub fn steps(&self) -> usize {
        self.alphas.len()
    }
}

/// Standard normal draws for `rows_per` rows of `cols` per generator, generator `i`'s rows first-to-last in block
/// `i`: `[generators · rows_per, cols]`.
pub fn normal_rows(generators: &mut [&mut Noise], rows_per: usize, cols: usize, device: &Device) -> Result<Tensor> {
    let values: Vec<f32> = generators
        .iter_mut()
        .flat_map(|g| g.normals_f32(rows_per * cols))
        .collect();
    Ok(Tensor::from_vec(values, (generators.len() * rows_per, cols), device)?)
}

/// How the sampler runs and which candidate is played.
#[derive(Debug, Clone, PartialEq)]
pub struct Sampler {
    pub schedule: Schedule,
    pub candidates: usize,
    pub clip: bool,
    pub temperature: f64,
}

impl Sampler {
    /// DDPM from `x_T ~ N(0, I)` to `x_0` for `obs` (one row per candidate, `[R, obs]`); generator `i` draws every
    /// number of the candidates in rows `i·candidates ..`.
    pub fn sample(&self, net: &NoiseNet, obs: &Tensor, generators: &mut [&mut Noise]) -> Result<Tensor> {
        let (rows, _) = obs.dims2()?;
        let act_dim = net.shape.act_dim;
        let device = obs.device();
        let mut x = normal_rows(generators, self.candidates, act_dim, device)?;
        let s = &self.schedule;
        for t in (0..s.steps()).rev() {
            let times = Tensor::full(t as f32, (rows, 1), device)?;
            let eps = net.forward(obs, &x, &times, None)?;
            let step = (1.0 - s.alphas[t]) / (1.0 - s.alpha_hats[t]).sqrt();
            x = x.sub(&eps.affine(step, 0.0)?)?.affine(1.0 / s.alphas[t].sqrt(), 0.0)?;
            if t > 0 {
                let z = normal_rows(generators, self.candidates, act_dim, device)?;
                x = x.add(&z.affine(s.betas[t].sqrt() * self.temperature, 0.0)?)?;
            }
            if self.clip {
                x = x.clamp(-1f32, 1f32)?;
            }
        }
        Ok(x.clamp(-1f32, 1f32)?)
    }
}

/// A diffusion policy at evaluation: the (EMA) noise network, its sampler, and the critic ensemble that ranks the
/// candidates.
pub struct DiffusionPolicy {
    pub net: NoiseNet,
    pub sampler: Sampler,
    pub critic: Ensemble,
    pub choice: CandidateChoice,
    pub max_action: f64,
}

impl DiffusionPolicy {
    /// The critic ensemble `<choice's prefix>.<j>` of `members` ReLU MLPs `[obs + act, hidden.., 1]`.
    pub fn critic_from_weights(
        choice: CandidateChoice,
        members: usize,
        input_dim: usize,
        hidden: &[usize],
        w: &mut Weights,
    ) -> Result<Ensemble> {
        let sizes = layer_sizes(input_dim, hidden, 1);
        let nets = (0..members)
            .map(|j| w.mlp(&format!("{}.{j}", choice.critic_prefix()), &sizes, Activation::Relu))
            .collect::<Result<Vec<Mlp>>>()?;
        Ok(Ensemble { nets })
    }

    /// Actions `[states, act]` for `obs` (`[states, obs]`), slot `i`'s candidates drawn from `generators[i]`.
    pub fn act(&self, obs: &Tensor, generators: &mut [&mut Noise]) -> Result<Vec<f32>> {
        let n = self.sampler.candidates;
        let (states, _) = obs.dims2()?;
        let repeated = repeat_rows(obs, n)?;
        let candidates = self.sampler.sample(&self.net, &repeated, generators)?;
        let values = self.critic.values(&crate::offline::concat(&repeated, &candidates)?)?;
        let ranked = match self.choice {
            // Lowest of the maxima: negate, so both choices take the highest.
            CandidateChoice::MinCostQ => Ensemble::max(&values)?.neg()?,
            CandidateChoice::MaxRewardQ => Ensemble::min(&values)?,
        };
        let scores = ranked.to_vec1::<f32>()?;
        let all = candidates.to_vec2::<f32>()?;
        let mut out = Vec::with_capacity(states * self.net.shape.act_dim);
        for s in 0..states {
            let block = &scores[s * n..(s + 1) * n];
            // The first of equal scores, and NaN never wins (it is then reported by the caller's finiteness check
            // through the candidate it would have picked, had every score been NaN).
            let best = (0..n).fold(0, |best, i| {
                if block[i] > block[best] || block[best].is_nan() {
                    i
                } else {
                    best
                }
            });
            out.extend(all[s * n + best].iter().map(|a| a * self.max_action as f32));
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shape() -> DiffusionShape {
        DiffusionShape {
            obs_dim: 3,
            act_dim: 2,
            time_dim: 8,
            cond_sizes: vec![16, 16],
            hidden_dim: 8,
            num_blocks: 2,
            layer_norm: true,
        }
    }

    #[test]
    fn the_vp_schedule_matches_fisors_constants_for_five_steps() {
        let s = Schedule::vp(5, 0.1, 10.0);
        let alphas = [0.80413, 0.54118, 0.36422, 0.24512, 0.16497];
        let hats = [0.80413, 0.43518, 0.15850, 0.038852, 0.0064093];
        for t in 0..5 {
            assert!((s.alphas[t] - alphas[t]).abs() < 1e-5, "{:?}", s.alphas);
            assert!(
                (s.alpha_hats[t] - hats[t]).abs() < 1e-5 * hats[t].max(0.01) * 100.0,
                "{:?}",
                s.alpha_hats
            );
            assert!((s.alphas[t] + s.betas[t] - 1.0).abs() < 1e-15);
        }
    }

    #[test]
    fn mish_and_the_network_follow_their_definitions() {
        let x = Tensor::new(&[-30.0f32, -1.0, 0.0, 2.0, 40.0], &Device::Cpu).unwrap();
        let got = mish(&x).unwrap().to_vec1::<f32>().unwrap();
        for (g, x) in got.iter().zip([-30.0f64, -1.0, 0.0, 2.0, 40.0]) {
            let want = x * (1.0 + x.exp()).ln().tanh();
            assert!((f64::from(*g) - want).abs() < 1e-5, "mish({x}) = {g}, want {want}");
        }

        // One row by hand: features, conditioning, input, blocks, output.
        let net = NoiseNet::new(shape(), &mut Noise::seeded(1)).unwrap();
        let obs = Tensor::new(&[[0.5f32, -0.25, 1.0]], &Device::Cpu).unwrap();
        let act = Tensor::new(&[[0.1f32, -0.3]], &Device::Cpu).unwrap();
        let t = Tensor::new(&[[3.0f32]], &Device::Cpu).unwrap();
        let got = net.forward(&obs, &act, &t, None).unwrap().to_vec2::<f32>().unwrap()[0].clone();
        let vars: std::collections::HashMap<String, Vec<f32>> = net
            .named_vars("a")
            .into_iter()
            .map(|(n, v)| (n, v.as_tensor().flatten_all().unwrap().to_vec1::<f32>().unwrap()))
            .collect();
        let dense = |name: &str, x: &[f64]| -> Vec<f64> {
            let (w, b) = (&vars[&format!("{name}.weight")], &vars[&format!("{name}.bias")]);
            (0..b.len())
                .map(|o| {
                    f64::from(b[o])
                        + x.iter()
                            .enumerate()
                            .map(|(i, xi)| f64::from(w[o * x.len() + i]) * xi)
                            .sum::<f64>()
                })
                .collect()
        };
        let m = |v: Vec<f64>| -> Vec<f64> { v.into_iter().map(|x| x * (1.0 + x.exp()).ln().tanh()).collect() };
        let kernel = &vars["a.time.kernel"];
        let f: Vec<f64> = kernel
            .iter()
            .map(|w| std::f64::consts::TAU * 3.0 * f64::from(*w))
            .collect();
        let features: Vec<f64> = f.iter().map(|v| v.cos()).chain(f.iter().map(|v| v.sin())).collect();
        let cond = dense("a.cond.1", &m(dense("a.cond.0", &features)));
        let input: Vec<f64> = [0.1, -0.3, 0.5, -0.25, 1.0].into_iter().chain(cond).collect();
        let mut h = dense("a.input", &input);
        for k in 0..2 {
            let mean = h.iter().sum::<f64>() / h.len() as f64;
            let var = h.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / h.len() as f64;
            let normed: Vec<f64> = h.iter().map(|x| (x - mean) / (var + 1e-5).sqrt()).collect();
            let y = dense(
                &format!("a.blocks.{k}.project"),
                &m(dense(&format!("a.blocks.{k}.expand"), &normed)),
            );
            h = h.iter().zip(y).map(|(a, b)| a + b).collect();
        }
        let want = dense("a.output", &m(h));
        for (g, w) in got.iter().zip(&want) {
            assert!((f64::from(*g) - w).abs() < 1e-4, "{got:?} vs {want:?}");
        }
    }

    #[test]
    fn the_sampler_denoises_by_the_ddpm_step_and_repeats_with_the_seed() {
        let net = NoiseNet::new(shape(), &mut Noise::seeded(2)).unwrap();
        let sampler = Sampler {
            schedule: Schedule::vp(3, 0.1, 10.0),
            candidates: 4,
            clip: true,
            temperature: 1.0,
        };
        let obs = repeat_rows(
            &Tensor::new(&[[0.5f32, -0.25, 1.0], [0.0, 1.0, 2.0]], &Device::Cpu).unwrap(),
            4,
        )
        .unwrap();
        let draw = |seeds: [u64; 2]| {
            let (mut a, mut b) = (Noise::seeded(seeds[0]), Noise::seeded(seeds[1]));
            sampler
                .sample(&net, &obs, &mut [&mut a, &mut b])
                .unwrap()
                .to_vec2::<f32>()
                .unwrap()
        };
        let one = draw([7, 8]);
        assert_eq!(one, draw([7, 8]));
        assert!(one.iter().flatten().all(|a| (-1.0..=1.0).contains(a)));
        // State 0's candidates depend on its own generator only.
        let other = draw([7, 9]);
        assert_eq!(one[..4], other[..4]);
        assert_ne!(one[4..], other[4..]);

        // By hand for state 0: the same draws, the same three steps.
        let mut g = Noise::seeded(7);
        let s = &sampler.schedule;
        let mut x = Tensor::from_vec(g.normals_f32(8), (4, 2), &Device::Cpu).unwrap();
        let obs0 = obs.narrow(0, 0, 4).unwrap();
        for t in (0..3).rev() {
            let eps = net
                .forward(&obs0, &x, &Tensor::full(t as f32, (4, 1), &Device::Cpu).unwrap(), None)
                .unwrap();
            let mean = (x.to_vec2::<f32>().unwrap().concat().iter())
                .zip(eps.to_vec2::<f32>().unwrap().concat())
                .map(|(x, e)| {
                    (f64::from(*x) - (1.0 - s.alphas[t]) / (1.0 - s.alpha_hats[t]).sqrt() * f64::from(e))
                        / s.alphas[t].sqrt()
                })
                .collect::<Vec<f64>>();
            let z = if t > 0 { g.normals_f32(8) } else { vec![0.0; 8] };
            let next: Vec<f32> = mean
                .iter()
                .zip(z)
                .map(|(m, z)| (m + s.betas[t].sqrt() * f64::from(z)).clamp(-1.0, 1.0) as f32)
                .collect();
            x = Tensor::from_vec(next, (4, 2), &Device::Cpu).unwrap();
        }
        for (a, b) in x.to_vec2::<f32>().unwrap().concat().iter().zip(one[..4].concat()) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
    }
}
