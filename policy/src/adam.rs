//! Adam (Kingma & Ba) with optional global gradient-norm clipping. Written here rather than taken from candle-nn
//! because its moments must go into training checkpoints: a resumed run continues with the same optimizer state.

use std::collections::HashMap;

use candle_core::Tensor;
use candle_core::backprop::GradStore;

use crate::{PolicyError, Result, Var};

pub struct Adam {
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    pub max_grad_norm: Option<f64>,
    /// Decoupled weight decay (AdamW, Loshchilov & Hutter; PyTorch's `AdamW`): each parameter is first multiplied by
    /// `1 − lr·weight_decay`, then takes the Adam step. 0 is plain Adam.
    pub weight_decay: f64,
    /// Keep each step's gradients (before clipping) for `last_gradients`: tests/parity holds them to PyTorch's.
    pub keep_gradients: bool,
    last_gradients: Vec<(usize, Tensor)>,
    steps: u64,
    params: Vec<Param>,
}

struct Param {
    name: String,
    var: Var,
    moments: Moments,
}

/// A parameter's first and second moments: on the host for a variable on the CPU (one pass over plain slices, the
/// fastest there), on the variable's device otherwise (a GPU keeps the update on the GPU instead of copying every
/// weight, gradient and moment to the host and back each step). Both do the same float32 operations in the same
/// order, so on the CPU they give the same bits (a test checks it).
enum Moments {
    /// Flat, in the variable's element order.
    Host {
        m: Vec<f32>,
        v: Vec<f32>,
    },
    Device {
        m: Tensor,
        v: Tensor,
    },
}

impl Moments {
    fn zeros(var: &Var, on_device: bool) -> Result<Moments> {
        Ok(if on_device {
            Moments::Device {
                m: var.as_tensor().zeros_like()?,
                v: var.as_tensor().zeros_like()?,
            }
        } else {
            let n = var.elem_count();
            Moments::Host {
                m: vec![0.0; n],
                v: vec![0.0; n],
            }
        })
    }
}

impl Adam {
    pub fn new(named_vars: Vec<(String, Var)>, lr: f64, max_grad_norm: Option<f64>) -> Result<Adam> {
        let params = named_vars
            .into_iter()
            .map(|(name, var)| {
                let moments = Moments::zeros(&var, !var.device().is_cpu())?;
                Ok(Param { name, var, moments })
            })
            .collect::<Result<_>>()?;
        Ok(Adam {
            lr,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            max_grad_norm,
            weight_decay: 0.0,
            keep_gradients: false,
            last_gradients: Vec::new(),
            steps: 0,
            params,
        })
    }

    /// Keeps every moment as a tensor beside its variable and updates with tensor operations, as on a GPU, even for
    /// variables on the CPU (tests hold the two forms to each other there).
    pub fn with_device_moments(mut self) -> Result<Adam> {
        for p in &mut self.params {
            p.moments = Moments::zeros(&p.var, true)?;
        }
        Ok(self)
    }

    /// AdamW: Adam with decoupled weight decay (see [`Adam::weight_decay`]).
    pub fn adamw(
        named_vars: Vec<(String, Var)>,
        lr: f64,
        weight_decay: f64,
        max_grad_norm: Option<f64>,
    ) -> Result<Adam> {
        let mut adam = Adam::new(named_vars, lr, max_grad_norm)?;
        adam.weight_decay = weight_decay;
        Ok(adam)
    }

    /// One update from the gradients of a loss; returns the gradient norm before clipping.
    ///
    /// The update runs as one pass over each parameter's values rather than as a chain of tensor operations (each
    /// of which would allocate a parameter-sized tensor): a third of a BC step's time went there. The arithmetic
    /// is the same float32 operations in the same order as the tensor chain it replaces (candle's `affine` is
    /// `x·mul + add` in float32), so a training run gives the same weights as before the change.
    pub fn step(&mut self, grads: &GradStore) -> Result<f64> {
        let gs: Vec<Option<Tensor>> = self
            .params
            .iter()
            .map(|p| grads.get(p.var.as_tensor()).cloned())
            .collect();
        if self.keep_gradients {
            self.last_gradients = gs
                .iter()
                .enumerate()
                .filter_map(|(i, g)| Some((i, g.clone()?)))
                .collect();
        }
        // ‖g‖ over all tensors. Clipping decides with candle's own float32 sums, as it always has (its vectorized
        // sum rounds differently from a plain loop), fetched from the device in one copy; without clipping the norm
        // is only reported, summed on the host where the gradients are copied there anyway.
        let host = self.params.iter().all(|p| matches!(p.moments, Moments::Host { .. }));
        let mut sq = 0.0f64;
        if self.max_grad_norm.is_some() || !host {
            sq = squared_sums(&gs)?.into_iter().map(f64::from).sum();
        }
        let host_grads: Vec<Option<Vec<f32>>> = if host {
            gs.iter()
                .map(|g| g.as_ref().map(|g| g.flatten_all()?.to_vec1::<f32>()).transpose())
                .collect::<candle_core::Result<_>>()?
        } else {
            vec![None; gs.len()]
        };
        if self.max_grad_norm.is_none() && host {
            for g in host_grads.iter().flatten() {
                sq += g.iter().map(|x| f64::from(*x).powi(2)).sum::<f64>();
            }
        }
        let norm = sq.sqrt();
        let scale = match self.max_grad_norm {
            Some(max) if norm > max => max / (norm + 1e-6),
            _ => 1.0,
        };
        self.steps += 1;
        let t = self.steps as i32;
        let (c1, c2) = (1.0 - self.beta1.powi(t), 1.0 - self.beta2.powi(t));
        let f = |x: f64| x as f32;
        let (b1, one_minus_b1, b2, one_minus_b2) =
            (f(self.beta1), f(1.0 - self.beta1), f(self.beta2), f(1.0 - self.beta2));
        let (inv_c1, inv_c2, eps, lr, scale32) = (f(1.0 / c1), f(1.0 / c2), f(self.eps), f(self.lr), f(scale));
        let decay = f(1.0 - self.lr * self.weight_decay);
        for ((p, g), host_g) in self.params.iter_mut().zip(&gs).zip(host_grads) {
            match &mut p.moments {
                Moments::Host { m, v } => {
                    let Some(mut g) = host_g else { continue };
                    if scale != 1.0 {
                        g.iter_mut().for_each(|x| *x *= scale32);
                    }
                    let mut values = p.var.as_tensor().flatten_all()?.to_vec1::<f32>()?;
                    if self.weight_decay != 0.0 {
                        values.iter_mut().for_each(|x| *x *= decay);
                    }
                    for (((x, m), v), g) in values.iter_mut().zip(m.iter_mut()).zip(v.iter_mut()).zip(&g) {
                        *m = *m * b1 + *g * one_minus_b1;
                        *v = *v * b2 + (*g * *g) * one_minus_b2;
                        let update = (*m * inv_c1) / ((*v * inv_c2).sqrt() + eps);
                        *x -= update * lr;
                    }
                    p.var.set(&Tensor::from_vec(values, p.var.shape(), p.var.device())?)?;
                }
                Moments::Device { m, v } => {
                    let Some(g) = g else { continue };
                    // candle's affine is `x·mul + add` in float32: the host loop's operations, one tensor each.
                    let g = if scale != 1.0 { g.affine(scale, 0.0)? } else { g.clone() };
                    let mut x = p.var.as_tensor().clone();
                    if self.weight_decay != 0.0 {
                        x = x.affine(f64::from(decay), 0.0)?;
                    }
                    *m = m
                        .affine(f64::from(b1), 0.0)?
                        .add(&g.affine(f64::from(one_minus_b1), 0.0)?)?;
                    *v = v
                        .affine(f64::from(b2), 0.0)?
                        .add(&g.sqr()?.affine(f64::from(one_minus_b2), 0.0)?)?;
                    let update = m
                        .affine(f64::from(inv_c1), 0.0)?
                        .div(&v.affine(f64::from(inv_c2), 0.0)?.sqrt()?.affine(1.0, f64::from(eps))?)?;
                    p.var.set(&x.sub(&update.affine(f64::from(lr), 0.0)?)?)?;
                }
            }
        }
        Ok(norm)
    }

    /// The gradients of the last step by the parameter's position in the optimizer (only with `keep_gradients`;
    /// a parameter the loss did not reach has none).
    pub fn last_gradients(&self) -> &[(usize, Tensor)] {
        &self.last_gradients
    }

    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// The moments as named tensors (`<prefix>.<param>.m`, `.v`) for a checkpoint.
    pub fn state(&self, prefix: &str) -> Vec<(String, Tensor)> {
        self.params
            .iter()
            .flat_map(|p| {
                let (m, v) = match &p.moments {
                    Moments::Host { m, v } => {
                        let t = |values: &[f32]| {
                            Tensor::from_slice(values, p.var.shape(), p.var.device())
                                .expect("the moments have the variable's element count")
                        };
                        (t(m), t(v))
                    }
                    Moments::Device { m, v } => (m.clone(), v.clone()),
                };
                [("m", m), ("v", v)].map(|(suffix, t)| (format!("{prefix}.{}.{suffix}", p.name), t))
            })
            .collect()
    }

    /// Restores moments written by [`Adam::state`] and the step count.
    pub fn restore(&mut self, prefix: &str, tensors: &HashMap<String, Tensor>, steps: u64) -> Result<()> {
        for p in &mut self.params {
            let read = |suffix: &str| -> Result<Tensor> {
                let name = format!("{prefix}.{}.{suffix}", p.name);
                let t = tensors
                    .get(&name)
                    .ok_or_else(|| PolicyError::Format(format!("optimizer state {name} is missing")))?;
                if t.dims() != p.var.dims() {
                    return Err(PolicyError::Format(format!(
                        "optimizer state {name} has the wrong shape"
                    )));
                }
                Ok(t.clone())
            };
            let (m, v) = (read("m")?, read("v")?);
            p.moments = match p.moments {
                Moments::Host { .. } => Moments::Host {
                    m: m.flatten_all()?.to_vec1::<f32>()?,
                    v: v.flatten_all()?.to_vec1::<f32>()?,
                },
                Moments::Device { .. } => Moments::Device {
                    m: m.to_device(p.var.device())?,
                    v: v.to_device(p.var.device())?,
                },
            };
        }
        self.steps = steps;
        Ok(())
    }
}

/// Σ g² of each gradient present, as candle's float32 sums, copied to the host in one transfer.
fn squared_sums(gs: &[Option<Tensor>]) -> Result<Vec<f32>> {
    let sums = gs
        .iter()
        .flatten()
        .map(|g| g.sqr()?.sum_all()?.reshape(1))
        .collect::<candle_core::Result<Vec<_>>>()?;
    if sums.is_empty() {
        return Ok(Vec::new());
    }
    Ok(Tensor::cat(&sums, 0)?.to_vec1::<f32>()?)
}

#[cfg(test)]
mod tests {
    use candle_core::Device;

    use super::*;

    #[test]
    fn first_step_moves_each_weight_by_lr_against_its_gradient_sign() {
        // With bias correction, Adam's first step is lr · g / (|g| + eps) per coordinate.
        let w = Var::from_vec(vec![1.0f32, -2.0, 0.5], 3, &Device::Cpu).unwrap();
        let mut adam = Adam::new(vec![("w".into(), w.clone())], 0.1, None).unwrap();
        // loss = Σ w² → gradient 2w.
        let grads = w.as_tensor().sqr().unwrap().sum_all().unwrap().backward().unwrap();
        adam.step(&grads).unwrap();
        let got = w.as_tensor().to_vec1::<f32>().unwrap();
        for (g, want) in got.iter().zip([0.9f32, -1.9, 0.4]) {
            assert!((g - want).abs() < 1e-6, "{got:?}");
        }
        // Its state round-trips.
        let state: HashMap<String, Tensor> = adam.state("opt").into_iter().collect();
        let mut again = Adam::new(vec![("w".into(), w.clone())], 0.1, None).unwrap();
        again.restore("opt", &state, adam.steps()).unwrap();
        assert_eq!(again.steps(), 1);
        assert_eq!(
            state["opt.w.m"].to_vec1::<f32>().unwrap(),
            again.state("opt")[0].1.to_vec1::<f32>().unwrap()
        );
    }

    #[test]
    fn adamw_decays_each_weight_before_the_adam_step_as_pytorch() {
        // PyTorch AdamW: w ← w·(1 − lr·wd), then w ← w − lr·m̂/(√v̂ + eps); the first step's Adam part is lr·sign(g).
        let w = Var::from_vec(vec![1.0f32, -2.0], 2, &Device::Cpu).unwrap();
        let mut adam = Adam::adamw(vec![("w".into(), w.clone())], 0.1, 0.5, None).unwrap();
        let grads = w.as_tensor().sqr().unwrap().sum_all().unwrap().backward().unwrap();
        adam.step(&grads).unwrap();
        let got = w.as_tensor().to_vec1::<f32>().unwrap();
        for (g, want) in got.iter().zip([1.0f32 * 0.95 - 0.1, -2.0 * 0.95 + 0.1]) {
            assert!((g - want).abs() < 1e-6, "{got:?}");
        }
    }

    /// loss = Σ w³/3, whose gradient is w².
    fn cubic_loss(w: &Var) -> Tensor {
        w.as_tensor()
            .powf(3.0)
            .unwrap()
            .sum_all()
            .unwrap()
            .affine(1.0 / 3.0, 0.0)
            .unwrap()
    }

    /// The update as the chain of candle tensor operations it replaced.
    fn tensor_chain_step(w: &Var, m: &mut Tensor, v: &mut Tensor, g: &Tensor, t: i32, lr: f64, scale: f64) {
        let (b1, b2, eps) = (0.9f64, 0.999f64, 1e-8);
        let (c1, c2) = (1.0 - b1.powi(t), 1.0 - b2.powi(t));
        let g = if scale != 1.0 {
            g.affine(scale, 0.0).unwrap()
        } else {
            g.clone()
        };
        *m = m
            .affine(b1, 0.0)
            .unwrap()
            .add(&g.affine(1.0 - b1, 0.0).unwrap())
            .unwrap();
        *v = v
            .affine(b2, 0.0)
            .unwrap()
            .add(&g.sqr().unwrap().affine(1.0 - b2, 0.0).unwrap())
            .unwrap();
        let update = m
            .affine(1.0 / c1, 0.0)
            .unwrap()
            .div(
                &v.affine(1.0 / c2, 0.0)
                    .unwrap()
                    .sqrt()
                    .unwrap()
                    .affine(1.0, eps)
                    .unwrap(),
            )
            .unwrap();
        w.set(&w.as_tensor().sub(&update.affine(lr, 0.0).unwrap()).unwrap())
            .unwrap();
    }

    #[test]
    fn the_update_equals_the_tensor_chain_bit_for_bit() {
        let init: Vec<f32> = (0..1000).map(|i| ((i * 37 % 101) as f32 - 50.0) / 17.0).collect();
        let (ours, theirs) = (
            Var::from_vec(init.clone(), (10, 100), &Device::Cpu).unwrap(),
            Var::from_vec(init, (10, 100), &Device::Cpu).unwrap(),
        );
        let mut adam = Adam::new(vec![("w".into(), ours.clone())], 1e-3, Some(0.5)).unwrap();
        let (mut m, mut v) = (
            theirs.as_tensor().zeros_like().unwrap(),
            theirs.as_tensor().zeros_like().unwrap(),
        );
        for t in 1..=5 {
            let norm = adam.step(&cubic_loss(&ours).backward().unwrap()).unwrap();
            let grads = cubic_loss(&theirs).backward().unwrap();
            let g = grads.get(theirs.as_tensor()).unwrap();
            let scale = 0.5 / (norm + 1e-6);
            tensor_chain_step(&theirs, &mut m, &mut v, g, t, 1e-3, scale);
            assert_eq!(
                ours.as_tensor().flatten_all().unwrap().to_vec1::<f32>().unwrap(),
                theirs.as_tensor().flatten_all().unwrap().to_vec1::<f32>().unwrap(),
                "step {t}"
            );
        }
    }

    #[test]
    fn device_moments_give_the_host_loops_bits_and_round_trip() {
        // The GPU form of the update (moments as tensors, tensor operations), run on the CPU: the same bits as the
        // host loop, with clipping and weight decay, and its state restores into either form.
        let init: Vec<f32> = (0..600).map(|i| ((i * 37 % 101) as f32 - 50.0) / 17.0).collect();
        let fresh = || Var::from_vec(init.clone(), (6, 100), &Device::Cpu).unwrap();
        let (host_w, device_w) = (fresh(), fresh());
        let make = |w: &Var| Adam::adamw(vec![("w".into(), w.clone())], 1e-2, 0.1, Some(0.5)).unwrap();
        let mut host = make(&host_w);
        let mut device = make(&device_w).with_device_moments().unwrap();
        for t in 1..=5 {
            let a = host.step(&cubic_loss(&host_w).backward().unwrap()).unwrap();
            let b = device.step(&cubic_loss(&device_w).backward().unwrap()).unwrap();
            assert_eq!(a, b, "step {t}: gradient norms");
            assert_eq!(
                host_w.as_tensor().flatten_all().unwrap().to_vec1::<f32>().unwrap(),
                device_w.as_tensor().flatten_all().unwrap().to_vec1::<f32>().unwrap(),
                "step {t}"
            );
        }
        let values = |state: Vec<(String, Tensor)>| -> Vec<Vec<f32>> {
            state
                .into_iter()
                .map(|(_, t)| t.flatten_all().unwrap().to_vec1::<f32>().unwrap())
                .collect()
        };
        assert_eq!(values(host.state("opt")), values(device.state("opt")));
        let state: HashMap<String, Tensor> = device.state("opt").into_iter().collect();
        let mut restored = make(&device_w).with_device_moments().unwrap();
        restored.restore("opt", &state, device.steps()).unwrap();
        assert_eq!(values(restored.state("opt")), values(device.state("opt")));
    }

    #[test]
    fn gradient_norm_is_clipped() {
        let w = Var::from_vec(vec![3.0f32, 4.0], 2, &Device::Cpu).unwrap();
        let mut adam = Adam::new(vec![("w".into(), w.clone())], 0.01, Some(1.0)).unwrap();
        // loss = ½ Σ w² → gradient w, norm 5.
        let grads = w
            .as_tensor()
            .sqr()
            .unwrap()
            .sum_all()
            .unwrap()
            .affine(0.5, 0.0)
            .unwrap()
            .backward()
            .unwrap();
        let norm = adam.step(&grads).unwrap();
        assert!((norm - 5.0).abs() < 1e-5);
        // Clipping rescales both coordinates alike, so Adam's sign-like first step is unchanged.
        let got = w.as_tensor().to_vec1::<f32>().unwrap();
        assert!((got[0] - 2.99).abs() < 1e-5 && (got[1] - 3.99).abs() < 1e-5, "{got:?}");
        // The first moment saw the clipped gradient w/5: m = (1 − β1)·(0.6, 0.8).
        let m = adam.state("opt")[0].1.to_vec1::<f32>().unwrap();
        assert!((m[0] - 0.06).abs() < 1e-6 && (m[1] - 0.08).abs() < 1e-6, "{m:?}");
    }
}
