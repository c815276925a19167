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
    steps: u64,
    params: Vec<Param>,
}

struct Param {
    name: String,
    var: Var,
    m: Tensor,
    v: Tensor,
}

impl Adam {
    pub fn new(named_vars: Vec<(String, Var)>, lr: f64, max_grad_norm: Option<f64>) -> Result<Adam> {
        let params = named_vars
            .into_iter()
            .map(|(name, var)| {
                let m = var.as_tensor().zeros_like()?;
                let v = m.clone();
                Ok(Param { name, var, m, v })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Adam {
            lr,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            max_grad_norm,
            steps: 0,
            params,
        })
    }

    /// One update from the gradients of a loss; returns the gradient norm before clipping.
    pub fn step(&mut self, grads: &GradStore) -> Result<f64> {
        let gs: Vec<Option<Tensor>> = self
            .params
            .iter()
            .map(|p| grads.get(p.var.as_tensor()).cloned())
            .collect();
        let mut sq = 0.0f64;
        for g in gs.iter().flatten() {
            sq += f64::from(g.sqr()?.sum_all()?.to_scalar::<f32>()?);
        }
        let norm = sq.sqrt();
        let scale = match self.max_grad_norm {
            Some(max) if norm > max => max / (norm + 1e-6),
            _ => 1.0,
        };
        self.steps += 1;
        let t = self.steps as i32;
        let (c1, c2) = (1.0 - self.beta1.powi(t), 1.0 - self.beta2.powi(t));
        for (p, g) in self.params.iter_mut().zip(gs) {
            let Some(g) = g else { continue };
            let g = if scale != 1.0 { g.affine(scale, 0.0)? } else { g };
            p.m = p.m.affine(self.beta1, 0.0)?.add(&g.affine(1.0 - self.beta1, 0.0)?)?;
            p.v =
                p.v.affine(self.beta2, 0.0)?
                    .add(&g.sqr()?.affine(1.0 - self.beta2, 0.0)?)?;
            let update =
                p.m.affine(1.0 / c1, 0.0)?
                    .div(&p.v.affine(1.0 / c2, 0.0)?.sqrt()?.affine(1.0, self.eps)?)?;
            p.var.set(&p.var.as_tensor().sub(&update.affine(self.lr, 0.0)?)?)?;
        }
        Ok(norm)
    }

    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// The moments as named tensors (`<prefix>.<param>.m`, `.v`) for a checkpoint.
    pub fn state(&self, prefix: &str) -> Vec<(String, Tensor)> {
        self.params
            .iter()
            .flat_map(|p| {
                [
                    (format!("{prefix}.{}.m", p.name), p.m.clone()),
                    (format!("{prefix}.{}.v", p.name), p.v.clone()),
                ]
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
                *slot = t.clone();
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
