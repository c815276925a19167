//! A multilayer perceptron whose layers are named like PyTorch's `nn.Sequential` of `nn.Linear`s
//! (`<prefix>.<i>.weight` of shape `[out, in]`, `<prefix>.<i>.bias`), so weights exported from PyTorch load as is.

use std::collections::HashMap;

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var};
use serde::{Deserialize, Serialize};

use crate::noise::Noise;
use crate::{PolicyError, Result};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Activation {
    Tanh,
    Relu,
}

impl Activation {
    pub fn apply(self, x: &Tensor) -> Result<Tensor> {
        Ok(match self {
            Activation::Tanh => x.tanh()?,
            Activation::Relu => crate::fused::relu(x)?,
        })
    }
}

/// Layer sizes `[input, hidden.., out]` of an MLP.
pub fn layer_sizes(input: usize, hidden: &[usize], out: usize) -> Vec<usize> {
    std::iter::once(input)
        .chain(hidden.iter().copied())
        .chain([out])
        .collect()
}

pub struct Mlp {
    prefix: String,
    /// (weight `[out, in]`, bias `[out]`) per layer.
    layers: Vec<(Var, Var)>,
    activation: Activation,
}

impl Mlp {
    /// Layer sizes `[in, hidden.., out]`; weights orthogonal (as `torch.nn.init.orthogonal_`) times `gain`, the
    /// last layer's times `last_gain`; biases zero.
    pub fn orthogonal(
        prefix: &str,
        sizes: &[usize],
        activation: Activation,
        gain: f64,
        last_gain: f64,
        noise: &mut Noise,
    ) -> Result<Mlp> {
        if sizes.len() < 2 || sizes.contains(&0) {
            return Err(PolicyError::Format(format!("bad layer sizes {sizes:?}")));
        }
        let mut layers = Vec::new();
        for (i, pair) in sizes.windows(2).enumerate() {
            let (fan_in, fan_out) = (pair[0], pair[1]);
            let g = if i + 2 == sizes.len() { last_gain } else { gain };
            let w: Vec<f32> = orthogonal(fan_out, fan_in, noise)
                .into_iter()
                .map(|x| (x * g) as f32)
                .collect();
            let weight = Var::from_vec(w, (fan_out, fan_in), &Device::Cpu)?;
            let bias = Var::zeros(fan_out, DType::F32, &Device::Cpu)?;
            layers.push((weight, bias));
        }
        Ok(Mlp {
            prefix: prefix.to_owned(),
            layers,
            activation,
        })
    }

    /// Layer sizes `[in, hidden.., out]` initialised as PyTorch's `nn.Linear` default: weights and biases uniform
    /// in ±1/√fan_in (kaiming-uniform with a = √5), which OSRL's critics and VAEs keep.
    pub fn pytorch_default(prefix: &str, sizes: &[usize], activation: Activation, noise: &mut Noise) -> Result<Mlp> {
        if sizes.len() < 2 || sizes.contains(&0) {
            return Err(PolicyError::Format(format!("bad layer sizes {sizes:?}")));
        }
        let mut layers = Vec::new();
        for pair in sizes.windows(2) {
            let (fan_in, fan_out) = (pair[0], pair[1]);
            let bound = 1.0 / (fan_in as f64).sqrt();
            let mut uniform =
                |n: usize| -> Vec<f32> { (0..n).map(|_| ((noise.uniform() * 2.0 - 1.0) * bound) as f32).collect() };
            let weight = Var::from_vec(uniform(fan_out * fan_in), (fan_out, fan_in), &Device::Cpu)?;
            let bias = Var::from_vec(uniform(fan_out), fan_out, &Device::Cpu)?;
            layers.push((weight, bias));
        }
        Ok(Mlp {
            prefix: prefix.to_owned(),
            layers,
            activation,
        })
    }

    /// The same network with its variables on `device` (initialised on the CPU from the seed, so the first weights
    /// are the same whichever device trains them); on the device it is already on, itself.
    pub fn to_device(self, device: &Device) -> Result<Mlp> {
        if self.layers[0].0.device().same_device(device) {
            return Ok(self);
        }
        let layers = self
            .layers
            .iter()
            .map(|(w, b)| {
                Ok((
                    Var::from_tensor(&w.as_tensor().to_device(device)?)?,
                    Var::from_tensor(&b.as_tensor().to_device(device)?)?,
                ))
            })
            .collect::<Result<_>>()?;
        Ok(Mlp { layers, ..self })
    }

    /// A copy whose variables are its own (a target network starts as one).
    pub fn copy(&self) -> Result<Mlp> {
        Ok(Mlp {
            prefix: self.prefix.clone(),
            layers: self
                .layers
                .iter()
                .map(|(w, b)| {
                    Ok((
                        Var::from_tensor(&w.as_tensor().copy()?)?,
                        Var::from_tensor(&b.as_tensor().copy()?)?,
                    ))
                })
                .collect::<Result<_>>()?,
            activation: self.activation,
        })
    }

    /// The layers stored under `prefix` in `tensors` (checked: consecutive, matching shapes, f32).
    pub fn from_tensors(prefix: &str, tensors: &HashMap<String, Tensor>, activation: Activation) -> Result<Mlp> {
        let mut layers = Vec::new();
        let mut last_out: Option<usize> = None;
        while let Some(weight) = tensors.get(&format!("{prefix}.{}.weight", layers.len())) {
            let i = layers.len();
            let bias = tensors
                .get(&format!("{prefix}.{i}.bias"))
                .ok_or_else(|| PolicyError::Format(format!("{prefix}.{i}.bias is missing")))?;
            let (out, inp) = weight
                .dims2()
                .map_err(|_| PolicyError::Format(format!("{prefix}.{i}.weight must be a matrix")))?;
            if bias.dims() != [out] {
                return Err(PolicyError::Format(format!(
                    "{prefix}.{i}.bias has shape {:?}, expected [{out}]",
                    bias.dims()
                )));
            }
            if let Some(prev) = last_out
                && prev != inp
            {
                return Err(PolicyError::Format(format!(
                    "{prefix}.{i}.weight takes {inp} inputs but the layer before gives {prev}"
                )));
            }
            if weight.dtype() != DType::F32 || bias.dtype() != DType::F32 {
                return Err(PolicyError::Format(format!("{prefix}.{i} must be float32")));
            }
            last_out = Some(out);
            // Copies: `Var::from_tensor` of a tensor that is already a variable would share (and later update)
            // its storage.
            layers.push((Var::from_tensor(&weight.copy()?)?, Var::from_tensor(&bias.copy()?)?));
        }
        if layers.is_empty() {
            return Err(PolicyError::Format(format!("no layer {prefix}.0.weight")));
        }
        Ok(Mlp {
            prefix: prefix.to_owned(),
            layers,
            activation,
        })
    }

    /// `[in, hidden.., out]`.
    pub fn sizes(&self) -> Vec<usize> {
        std::iter::once(self.input_dim())
            .chain(self.layers.iter().map(|(w, _)| w.dims()[0]))
            .collect()
    }

    pub fn input_dim(&self) -> usize {
        self.layers[0].0.dims()[1]
    }

    pub fn output_dim(&self) -> usize {
        self.layers[self.layers.len() - 1].0.dims()[0]
    }

    /// `x`: `[batch, in]` → `[batch, out]`, the activation between layers (none after the last).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let mut h = x.clone();
        for (i, (w, b)) in self.layers.iter().enumerate() {
            h = crate::fused::bias_add(&h.matmul(&w.as_tensor().t()?)?, b.as_tensor())?;
            if i + 1 < self.layers.len() {
                h = self.activation.apply(&h)?;
            }
        }
        Ok(h)
    }

    /// `mean((max_action · tanh(net(x)) − y)²)` (behaviour cloning's loss) and its gradient with respect to every
    /// layer, keyed by variable as candle's autograd returns them.
    ///
    /// The chain rule of this one network written out: a forward pass that keeps each layer's output, then one
    /// matrix product per weight gradient and per layer below. Autograd records and replays a graph of every
    /// intermediate tensor (transposes, broadcasts and their reductions); doing without made the BC step ~1.5×
    /// faster, enough to match PyTorch (BENCHMARKS.md). A test holds it to autograd's gradients.
    pub fn tanh_mse_gradients(&self, x: &Tensor, y: &Tensor, max_action: f64) -> Result<(f32, GradStore)> {
        // Each layer's input: x, then the activations of the hidden layers.
        let mut inputs = vec![x.clone()];
        let mut out = x.clone();
        for (i, (w, b)) in self.layers.iter().enumerate() {
            let z = out.matmul(&w.as_tensor().t()?)?.broadcast_add(b.as_tensor())?;
            if i + 1 == self.layers.len() {
                out = z.tanh()?;
            } else {
                out = self.activation.apply(&z)?;
                inputs.push(out.clone());
            }
        }
        // out = tanh(z_L); prediction = max_action · out.
        let diff = out.affine(max_action, 0.0)?.sub(y)?;
        let n = diff.elem_count() as f64;
        let loss = diff.sqr()?.mean_all()?.to_scalar::<f32>()?;
        // ∂loss/∂z_L = 2/n · diff · max_action · (1 − tanh²).
        let mut grad = diff
            .affine(2.0 * max_action / n, 0.0)?
            .mul(&out.sqr()?.affine(-1.0, 1.0)?)?;
        let mut grads = GradStore::default();
        for (i, (w, b)) in self.layers.iter().enumerate().rev() {
            let input = &inputs[i];
            grads.insert(w.as_tensor(), grad.t()?.matmul(input)?);
            grads.insert(b.as_tensor(), grad.sum(0)?);
            if i > 0 {
                // Through the weights, then the activation that produced `input`.
                let upstream = grad.matmul(w.as_tensor())?;
                grad = match self.activation {
                    Activation::Relu => upstream.mul(&input.gt(0f32)?.to_dtype(DType::F32)?)?,
                    Activation::Tanh => upstream.mul(&input.sqr()?.affine(-1.0, 1.0)?)?,
                };
            }
        }
        Ok((loss, grads))
    }

    /// The parameters with their checkpoint names.
    pub fn named_vars(&self) -> Vec<(String, Var)> {
        self.layers
            .iter()
            .enumerate()
            .flat_map(|(i, (w, b))| {
                [
                    (format!("{}.{i}.weight", self.prefix), w.clone()),
                    (format!("{}.{i}.bias", self.prefix), b.clone()),
                ]
            })
            .collect()
    }
}

/// A `rows × cols` matrix with orthonormal rows or columns (whichever are fewer), from Gram–Schmidt on a Gaussian
/// matrix with the sign convention of a QR with positive diagonal, as PyTorch does.
fn orthogonal(rows: usize, cols: usize, noise: &mut Noise) -> Vec<f64> {
    let (tall, short) = (rows.max(cols), rows.min(cols));
    // `short` column vectors of length `tall`.
    let mut q: Vec<Vec<f64>> = (0..short)
        .map(|_| (0..tall).map(|_| noise.normal()).collect())
        .collect();
    for j in 0..short {
        let (done, rest) = q.split_at_mut(j);
        let v = &mut rest[0];
        for u in done.iter() {
            let dot: f64 = v.iter().zip(u).map(|(a, b)| a * b).sum();
            for (a, b) in v.iter_mut().zip(u) {
                *a -= dot * b;
            }
        }
        let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        for x in v.iter_mut() {
            *x /= norm;
        }
    }
    let mut out = vec![0.0; rows * cols];
    for r in 0..rows {
        for c in 0..cols {
            // Row-major [rows, cols]: columns of Q when rows >= cols, rows of Qᵀ otherwise.
            out[r * cols + c] = if rows >= cols { q[c][r] } else { q[r][c] };
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orthogonal_weights_have_orthonormal_rows_or_columns() {
        for (rows, cols) in [(8, 3), (3, 8), (5, 5)] {
            let w = orthogonal(rows, cols, &mut Noise::seeded(1));
            let (n, len) = (rows.min(cols), rows.max(cols));
            let vector = |i: usize, t: usize| if rows >= cols { w[t * cols + i] } else { w[i * cols + t] };
            for a in 0..n {
                for b in 0..n {
                    let dot: f64 = (0..len).map(|t| vector(a, t) * vector(b, t)).sum();
                    let want = if a == b { 1.0 } else { 0.0 };
                    assert!((dot - want).abs() < 1e-9, "{rows}x{cols}: <{a},{b}> = {dot}");
                }
            }
        }
    }

    #[test]
    fn written_out_gradients_equal_autograd() {
        let mut noise = Noise::seeded(12);
        for activation in [Activation::Relu, Activation::Tanh] {
            let net = Mlp::orthogonal("net", &[5, 16, 16, 3], activation, 1.4, 1.0, &mut noise).unwrap();
            let x = Tensor::from_vec(noise.normals_f32(32 * 5), (32, 5), &Device::Cpu).unwrap();
            let y = Tensor::from_vec(noise.normals_f32(32 * 3), (32, 3), &Device::Cpu)
                .unwrap()
                .tanh()
                .unwrap();
            let (loss, ours) = net.tanh_mse_gradients(&x, &y, 2.0).unwrap();
            let prediction = net.forward(&x).unwrap().tanh().unwrap().affine(2.0, 0.0).unwrap();
            let reference = prediction.sub(&y).unwrap().sqr().unwrap().mean_all().unwrap();
            assert!((loss - reference.to_scalar::<f32>().unwrap()).abs() < 1e-6);
            let theirs = reference.backward().unwrap();
            let flat = |t: Option<&Tensor>| t.unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
            for (name, var) in net.named_vars() {
                let (a, b) = (flat(ours.get(var.as_tensor())), flat(theirs.get(var.as_tensor())));
                assert_eq!(a.len(), b.len(), "{name}");
                let scale = b.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-6);
                for (u, v) in a.iter().zip(&b) {
                    assert!((u - v).abs() <= 1e-5 * scale, "{activation:?} {name}: {u} vs {v}");
                }
            }
        }
    }

    #[test]
    fn forward_matches_hand_arithmetic_and_round_trips_through_named_tensors() {
        let mlp = Mlp::orthogonal("net", &[2, 3, 1], Activation::Tanh, 1.0, 1.0, &mut Noise::seeded(5)).unwrap();
        let x = Tensor::from_vec(vec![0.3f32, -0.7], (1, 2), &Device::Cpu).unwrap();
        let got = mlp.forward(&x).unwrap().to_vec2::<f32>().unwrap()[0][0];
        let vars = mlp.named_vars();
        let w0 = vars[0].1.as_tensor().to_vec2::<f32>().unwrap();
        let w1 = vars[2].1.as_tensor().to_vec2::<f32>().unwrap();
        let hidden: Vec<f32> = w0.iter().map(|row| (row[0] * 0.3 + row[1] * -0.7).tanh()).collect();
        let want: f32 = w1[0].iter().zip(&hidden).map(|(w, h)| w * h).sum();
        assert!((got - want).abs() < 1e-6, "{got} vs {want}");

        let tensors: HashMap<String, Tensor> = vars.iter().map(|(n, v)| (n.clone(), v.as_tensor().clone())).collect();
        let back = Mlp::from_tensors("net", &tensors, Activation::Tanh).unwrap();
        assert_eq!(back.forward(&x).unwrap().to_vec2::<f32>().unwrap()[0][0], got);
        assert_eq!((back.input_dim(), back.output_dim()), (2, 1));

        let mut broken = tensors.clone();
        broken.insert(
            "net.1.weight".into(),
            Tensor::zeros((1, 4), DType::F32, &Device::Cpu).unwrap(),
        );
        let err = Mlp::from_tensors("net", &broken, Activation::Tanh)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("takes 4 inputs but the layer before gives 3"), "{err}");
    }
}
