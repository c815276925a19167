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
    /// The moments, flat, in the variable's element order.
    m: Vec<f32>,
    v: Vec<f32>,
}

impl Adam {
    pub fn new(named_vars: Vec<(String, Var)>, lr: f64, max_grad_norm: Option<f64>) -> Result<Adam> {
        let params = named_vars
            .into_iter()
            .map(|(name, var)| {
                let n = var.elem_count();
                Param {
                    name,
                    var,
                    m: vec![0.0; n],
                    v: vec![0.0; n],
                }
            })
            .collect();
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
        // sum rounds differently from a plain loop); without clipping the norm is only reported.
        let mut sq = 0.0f64;
        if self.max_grad_norm.is_some() {
            for g in gs.iter().flatten() {
                sq += f64::from(g.sqr()?.sum_all()?.to_scalar::<f32>()?);
            }
        }
        let gs: Vec<Option<Vec<f32>>> = gs
            .iter()
            .map(|g| g.as_ref().map(|g| g.flatten_all()?.to_vec1::<f32>()).transpose())
            .collect::<candle_core::Result<_>>()?;
        if self.max_grad_norm.is_none() {
            for g in gs.iter().flatten() {
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
        for (p, g) in self.params.iter_mut().zip(gs) {
            let Some(mut g) = g else { continue };
            if scale != 1.0 {
                g.iter_mut().for_each(|x| *x *= scale32);
            }
            let mut values = p.var.as_tensor().flatten_all()?.to_vec1::<f32>()?;
            if self.weight_decay != 0.0 {
                values.iter_mut().for_each(|x| *x *= decay);
            }
            for (((x, m), v), g) in values.iter_mut().zip(&mut p.m).zip(&mut p.v).zip(&g) {
                *m = *m * b1 + *g * one_minus_b1;
                *v = *v * b2 + (*g * *g) * one_minus_b2;
                let update = (*m * inv_c1) / ((*v * inv_c2).sqrt() + eps);
                *x -= update * lr;
            }
            p.var.set(&Tensor::from_vec(values, p.var.shape(), p.var.device())?)?;
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
                [("m", &p.m), ("v", &p.v)].map(|(suffix, values)| {
                    let t = Tensor::from_slice(values, p.var.shape(), p.var.device())
                        .expect("the moments have the variable's element count");
                    (format!("{prefix}.{}.{suffix}", p.name), t)
                })
            })
            .collect()
    }

    /// Restores moments written by [`Adam::state`] and the step count.
    pub fn restore(&mut self, prefix: &str, tensors: &HashMap<String, Tensor>, steps: u64) -> Result<()> {
        for p in &mut self.params {
            for (suffix, slot) in [("m", &mut p.m), ("v", &mut p.v)] {
                let name = format!("{prefix}.{}.{suffix}", p.name);
                let t = tensors
                    .get(&name)
                    .ok_or_else(|| PolicyError::Format(format!("optimizer state {name} is missing")))?;
                if t.dims() != p.var.dims() {
                    return Err(PolicyError::Format(format!(
                        "optimizer state {name} has the wrong shape"
                    )));
                }
                *slot = t.flatten_all()?.to_vec1::<f32>()?;
            }
        }
        self.steps = steps;
        Ok(())
    }
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
            // loss = Σ w³/3 → gradient w².
            let loss = |w: &Var| {
                w.as_tensor()
                    .powf(3.0)
                    .unwrap()
                    .sum_all()
                    .unwrap()
                    .affine(1.0 / 3.0, 0.0)
                    .unwrap()
            };
            let norm = adam.step(&loss(&ours).backward().unwrap()).unwrap();
            let grads = loss(&theirs).backward().unwrap();
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
