//! The building blocks of the sequence and BCQ architectures, named like their PyTorch modules (`<name>.weight`,
//! `<name>.bias`) so a `state_dict` exported from PyTorch loads as is, and [`Weights`]: reading named tensors out of
//! a checkpoint with a shape check for each and a record of which were used.

use std::collections::{BTreeSet, HashMap};

use candle_core::{DType, Device, Tensor, Var};

use crate::mlp::Mlp;
use crate::noise::Noise;
use crate::{PolicyError, Result};

// Softmax and its log live with the composed operations (`fused::composed`), which need them and which this
// module's layers call: one direction between the two modules.
pub use crate::fused::composed::{log_softmax, softmax};

/// `nn.Linear`: `x · Wᵀ + b` over the last dimension of `x` (any leading dimensions).
pub struct Linear {
    pub weight: Var,
    pub bias: Var,
}

impl Linear {
    /// Weights `N(0, std²)` and zero biases (the Decision Transformer's initialisation, std 0.02).
    pub fn normal(inputs: usize, outputs: usize, std: f64, noise: &mut Noise) -> Result<Linear> {
        Ok(Linear {
            weight: normal_var(&[outputs, inputs], std, noise)?,
            bias: Var::zeros(outputs, DType::F32, &Device::Cpu)?,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let dims = x.dims().to_vec();
        let inputs = *dims
            .last()
            .ok_or_else(|| PolicyError::Format("a linear layer needs an input axis".into()))?;
        let rows = x.elem_count() / inputs.max(1);
        let y = crate::fused::bias_add(
            &x.reshape((rows, inputs))?.matmul(&self.weight.as_tensor().t()?)?,
            self.bias.as_tensor(),
        )?;
        let mut out = dims;
        *out.last_mut().expect("checked above") = self.weight.dims()[0];
        Ok(y.reshape(out)?)
    }

    pub fn named_vars(&self, name: &str) -> Vec<(String, Var)> {
        vec![
            (format!("{name}.weight"), self.weight.clone()),
            (format!("{name}.bias"), self.bias.clone()),
        ]
    }

    pub fn to_device(&self, device: &Device) -> Result<Linear> {
        Ok(Linear {
            weight: crate::var_on(&self.weight, device)?,
            bias: crate::var_on(&self.bias, device)?,
        })
    }
}

/// `nn.LayerNorm` over the last dimension (PyTorch's ε = 1e-5, biased variance).
pub struct LayerNorm {
    pub weight: Var,
    pub bias: Var,
}

impl LayerNorm {
    pub const EPS: f64 = 1e-5;

    /// Weight one, bias zero.
    pub fn new(dim: usize) -> Result<LayerNorm> {
        Ok(LayerNorm {
            weight: Var::ones(dim, DType::F32, &Device::Cpu)?,
            bias: Var::zeros(dim, DType::F32, &Device::Cpu)?,
        })
    }

    /// One fused operation ([`crate::fused::layer_norm`]) forward and backward.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(crate::fused::layer_norm(
            x,
            self.weight.as_tensor(),
            self.bias.as_tensor(),
            Self::EPS,
        )?)
    }

    pub fn named_vars(&self, name: &str) -> Vec<(String, Var)> {
        vec![
            (format!("{name}.weight"), self.weight.clone()),
            (format!("{name}.bias"), self.bias.clone()),
        ]
    }

    pub fn to_device(&self, device: &Device) -> Result<LayerNorm> {
        Ok(LayerNorm {
            weight: crate::var_on(&self.weight, device)?,
            bias: crate::var_on(&self.bias, device)?,
        })
    }
}

/// A float32 variable of the given shape with `N(0, std²)` entries.
pub fn normal_var(shape: &[usize], std: f64, noise: &mut Noise) -> Result<Var> {
    let n = shape.iter().product();
    let values: Vec<f32> = (0..n).map(|_| (noise.normal() * std) as f32).collect();
    Ok(Var::from_vec(values, shape, &Device::Cpu)?)
}

/// Named tensors being read into a network: each read checks presence, dtype and shape, and is remembered, so
/// [`Weights::finish`] can refuse tensors the declared architecture has no place for (a misnamed or surplus layer
/// would otherwise be ignored silently, and the network scored would not be the one trained).
pub struct Weights<'a> {
    tensors: &'a HashMap<String, Tensor>,
    used: BTreeSet<String>,
}

impl<'a> Weights<'a> {
    pub fn new(tensors: &'a HashMap<String, Tensor>) -> Weights<'a> {
        Weights {
            tensors,
            used: BTreeSet::new(),
        }
    }

    /// The float32 tensor `name` of exactly `shape`, as a fresh variable.
    pub fn var(&mut self, name: &str, shape: &[usize]) -> Result<Var> {
        let t = self
            .tensors
            .get(name)
            .ok_or_else(|| PolicyError::Format(format!("{name} is missing")))?;
        if t.dims() != shape {
            return Err(PolicyError::Format(format!(
                "{name} has shape {:?}, expected {shape:?}",
                t.dims()
            )));
        }
        if t.dtype() != DType::F32 {
            return Err(PolicyError::Format(format!(
                "{name} must be float32, not {:?}",
                t.dtype()
            )));
        }
        self.used.insert(name.to_owned());
        // A copy: `Var::from_tensor` of a tensor that is already a variable would share its storage.
        Ok(Var::from_tensor(&t.copy()?)?)
    }

    pub fn linear(&mut self, name: &str, inputs: usize, outputs: usize) -> Result<Linear> {
        Ok(Linear {
            weight: self.var(&format!("{name}.weight"), &[outputs, inputs])?,
            bias: self.var(&format!("{name}.bias"), &[outputs])?,
        })
    }

    /// A linear layer that only training uses (a prediction head): read and checked when present.
    pub fn optional_linear(&mut self, name: &str, inputs: usize, outputs: usize) -> Result<Option<Linear>> {
        if self.tensors.contains_key(&format!("{name}.weight")) || self.tensors.contains_key(&format!("{name}.bias")) {
            return self.linear(name, inputs, outputs).map(Some);
        }
        Ok(None)
    }

    pub fn layer_norm(&mut self, name: &str, dim: usize) -> Result<LayerNorm> {
        Ok(LayerNorm {
            weight: self.var(&format!("{name}.weight"), &[dim])?,
            bias: self.var(&format!("{name}.bias"), &[dim])?,
        })
    }

    /// The MLP `<prefix>.<i>` with layer sizes exactly `sizes`.
    pub fn mlp(&mut self, prefix: &str, sizes: &[usize], activation: crate::mlp::Activation) -> Result<Mlp> {
        let net = Mlp::from_tensors(prefix, self.tensors, activation)?;
        if net.sizes() != sizes {
            return Err(PolicyError::Format(format!(
                "{prefix} has layer sizes {:?}, but {} declares {sizes:?}",
                net.sizes(),
                crate::checkpoint::CONFIG_FILE
            )));
        }
        self.used.extend(net.named_vars().into_iter().map(|(name, _)| name));
        Ok(net)
    }

    /// Refuses the tensors nothing read, except those under `training_only` prefixes (parts of the module that only
    /// training uses, such as a VAE's encoder or a transformer's prediction heads).
    pub fn finish(self, training_only: &[&str]) -> Result<()> {
        let surplus: Vec<&String> = self
            .tensors
            .keys()
            .filter(|name| !self.used.contains(*name))
            .filter(|name| !training_only.iter().any(|p| name.starts_with(p)))
            .collect::<BTreeSet<_>>()
            .into_iter()
            .collect();
        if surplus.is_empty() {
            return Ok(());
        }
        let shown: Vec<&str> = surplus.iter().take(5).map(|s| s.as_str()).collect();
        Err(PolicyError::Format(format!(
            "{} tensor(s) have no place in the declared architecture: {}{}",
            surplus.len(),
            shown.join(", "),
            if surplus.len() > shown.len() { ", ..." } else { "" }
        )))
    }
}

#[cfg(test)]
mod tests {

    #[test]
    fn softmax_matches_the_fused_kernel_and_its_gradient_matches_finite_differences() {
        let x = Var::from_vec(vec![0.3f32, -1.0, 2.0, 0.5, 0.1, -0.2], (2, 3), &Device::Cpu).unwrap();
        let ours: Vec<Vec<f32>> = softmax(x.as_tensor(), 1).unwrap().to_vec2().unwrap();
        let fused: Vec<Vec<f32>> = candle_nn::ops::softmax_last_dim(x.as_tensor())
            .unwrap()
            .to_vec2()
            .unwrap();
        for (a, b) in ours.iter().flatten().zip(fused.iter().flatten()) {
            assert!((a - b).abs() < 1e-6);
        }
        let logs: Vec<Vec<f32>> = log_softmax(x.as_tensor(), 1).unwrap().to_vec2().unwrap();
        for (l, p) in logs.iter().flatten().zip(ours.iter().flatten()) {
            assert!((l.exp() - p).abs() < 1e-6);
        }
        // d/dx of Σ w ⊙ softmax(x) and of Σ w ⊙ log_softmax(x) against central differences.
        let w = Tensor::new(&[[1.0f32, -2.0, 0.5], [0.3, 0.7, -1.1]], &Device::Cpu).unwrap();
        for f in [softmax, log_softmax] {
            let loss = |x: &Tensor| f(x, 1).unwrap().mul(&w).unwrap().sum_all().unwrap();
            let grads = loss(x.as_tensor()).backward().unwrap();
            let g: Vec<f32> = grads
                .get(x.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let base: Vec<f32> = x.as_tensor().flatten_all().unwrap().to_vec1().unwrap();
            let h = 1e-2f32;
            for k in 0..6 {
                let at = |d: f32| {
                    let mut v = base.clone();
                    v[k] += d;
                    let t = Tensor::from_vec(v, (2, 3), &Device::Cpu).unwrap();
                    loss(&t).to_scalar::<f32>().unwrap()
                };
                let numeric = (at(h) - at(-h)) / (2.0 * h);
                assert!((numeric - g[k]).abs() < 2e-3, "{k}: {numeric} vs {}", g[k]);
            }
        }
    }

    use super::*;

    #[test]
    fn layer_norm_and_linear_match_their_definitions_over_leading_axes() {
        let x = Tensor::from_vec(vec![1f32, 2.0, 4.0, -1.0, 0.0, 1.0], (1, 2, 3), &Device::Cpu).unwrap();
        let norm = LayerNorm::new(3).unwrap();
        let got = norm
            .forward(&x)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        for (row, values) in [[1f64, 2.0, 4.0], [-1.0, 0.0, 1.0]].iter().enumerate() {
            let mean = values.iter().sum::<f64>() / 3.0;
            let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / 3.0;
            for (j, v) in values.iter().enumerate() {
                let want = (v - mean) / (var + LayerNorm::EPS).sqrt();
                assert!((f64::from(got[row * 3 + j]) - want).abs() < 1e-5, "{got:?}");
            }
        }
        let linear = Linear::normal(3, 2, 1.0, &mut Noise::seeded(4)).unwrap();
        let y = linear.forward(&x).unwrap();
        assert_eq!(y.dims(), [1, 2, 2]);
        let w = linear.weight.as_tensor().to_vec2::<f32>().unwrap();
        let y = y.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let want = -w[1][0] + w[1][2];
        assert!((y[3] - want).abs() < 1e-6);
    }

    #[test]
    fn weights_refuse_wrong_shapes_and_tensors_without_a_place() {
        let t = |shape: &[usize]| Tensor::zeros(shape, DType::F32, &Device::Cpu).unwrap();
        let tensors: HashMap<String, Tensor> = [
            ("a.weight".to_owned(), t(&[2, 3])),
            ("a.bias".to_owned(), t(&[2])),
            ("head.weight".to_owned(), t(&[1, 2])),
            ("stray".to_owned(), t(&[1])),
        ]
        .into_iter()
        .collect();
        let mut w = Weights::new(&tensors);
        let err = w.linear("a", 4, 2).err().unwrap().to_string();
        assert!(err.contains("a.weight has shape [2, 3], expected [2, 4]"), "{err}");
        w.linear("a", 3, 2).unwrap();
        let err = w.finish(&["head."]).err().unwrap().to_string();
        assert!(
            err.contains("1 tensor(s) have no place") && err.contains("stray"),
            "{err}"
        );
    }
}
