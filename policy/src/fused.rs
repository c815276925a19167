//! Elementwise and row-wise operations of the networks as single candle operations with their gradients written
//! out: a bias added over rows, ReLU, GELU, dropout, layer norm, and causal softmax.
//!
//! Why: candle's autograd keeps every intermediate tensor of a composite operation, and gives each one a gradient
//! that it zero-fills and then adds into. CDT trains at batch 2048 with 40 tokens, so each such tensor is 40–170 MB
//! (`[2048·40, 512]` after the first MLP layer, `[2048, 8, 40, 40]` attention weights). Built from primitives, GELU's
//! backward alone is ten passes over the largest of them, and layer norm and softmax are nine each way. In the
//! small MLPs of the Q-learning methods, candle's bias gradient (a strided reduction over the batch) and ReLU's
//! backward (a comparison, a conversion and a product) were a quarter of COptiDICE's step. Fused, each
//! operation reads its inputs once forward and once backward. The arithmetic is the same as the primitive forms
//! (`Linear::forward`'s broadcast add, `LayerNorm`'s mean/variance, a softmax over the unmasked positions; GELU's
//! error function is a polynomial within 1.5e-7 of candle's `gelu_erf`), and the tests hold each fused gradient to
//! autograd's through the primitive form.
//!
//! The fused kernels run on the CPU in float32 on contiguous tensors (the wrappers make them so). On any other
//! device (CUDA, with the `cuda` feature) each wrapper runs its [`composed`] form instead: the same arithmetic
//! built from candle's primitive operations, which candle's CUDA backend runs and differentiates. The tests hold
//! each fused operation to its composed form, forward and backward, so the two paths agree to float tolerance.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Shape, Storage, Tensor};

type CResult<T> = candle_core::Result<T>;

fn msg(text: String) -> candle_core::Error {
    candle_core::Error::Msg(text)
}

/// The float32 elements of a contiguous CPU layout.
fn slice<'a>(storage: &'a CpuStorage, layout: &Layout, op: &str) -> CResult<&'a [f32]> {
    let (start, end) = layout
        .contiguous_offsets()
        .ok_or_else(|| msg(format!("{op}: needs a contiguous tensor")))?;
    Ok(&storage.as_slice::<f32>()?[start..end])
}

/// Runs `f` on a tensor's float32 elements in row-major order (copying only if it is not contiguous).
fn with_elements<R>(t: &Tensor, op: &str, f: impl FnOnce(&[f32]) -> CResult<R>) -> CResult<R> {
    let t = t.contiguous()?;
    let (storage, layout) = t.storage_and_layout();
    match &*storage {
        Storage::Cpu(cpu) => f(slice(cpu, layout, op)?),
        _ => Err(msg(format!("{op}: runs on the CPU only"))),
    }
}

fn tensor(values: Vec<f32>, shape: &Shape) -> CResult<Tensor> {
    Tensor::from_vec(values, shape.clone(), &candle_core::Device::Cpu)
}

/// The length of the last axis, checked against a per-column parameter.
fn columns(shape: &Shape, op: &str, parameter: usize) -> CResult<usize> {
    let n = *shape.dims().last().ok_or_else(|| msg(format!("{op}: needs an axis")))?;
    if n != parameter {
        return Err(msg(format!("{op}: last axis {n} against a parameter of {parameter}")));
    }
    Ok(n)
}

/// Sums the rows of a row-major `[rows, n]` matrix.
fn column_sums(values: &[f32], n: usize) -> Vec<f32> {
    let mut sums = vec![0f32; n];
    for row in values.chunks_exact(n) {
        for (s, v) in sums.iter_mut().zip(row) {
            *s += v;
        }
    }
    sums
}

/// `y + b` with `b` added to every row over the last axis.
pub fn bias_add(y: &Tensor, bias: &Tensor) -> CResult<Tensor> {
    if !y.device().is_cpu() {
        return composed::bias_add(y, bias);
    }
    y.contiguous()?.apply_op2(&bias.contiguous()?, BiasAdd)
}

struct BiasAdd;

impl CustomOp2 for BiasAdd {
    fn name(&self) -> &'static str {
        "bias-add"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> CResult<(CpuStorage, Shape)> {
        let (y, b) = (slice(s1, l1, "bias-add")?, slice(s2, l2, "bias-add")?);
        let n = columns(l1.shape(), "bias-add", b.len())?;
        let mut out = y.to_vec();
        for row in out.chunks_exact_mut(n.max(1)) {
            for (o, b) in row.iter_mut().zip(b) {
                *o += b;
            }
        }
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }

    fn bwd(
        &self,
        _y: &Tensor,
        bias: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> CResult<(Option<Tensor>, Option<Tensor>)> {
        let n = bias.elem_count();
        let bias_grad = with_elements(grad, "bias-add", |g| tensor(column_sums(g, n.max(1)), bias.shape()))?;
        Ok((Some(grad.clone()), Some(bias_grad)))
    }
}

/// GELU with the error function, `x · Φ(x)` (PyTorch's default GELU and candle's `gelu_erf`); its slope is
/// `Φ(x) + x·φ(x)`.
pub fn gelu_erf(x: &Tensor) -> CResult<Tensor> {
    if !x.device().is_cpu() {
        return composed::gelu_erf(x);
    }
    x.contiguous()?.apply_op1(Elementwise {
        name: "gelu-erf",
        value: |x: f32| x * normal_cdf_pdf(x).0,
        slope: |x: f32| {
            let (cdf, pdf) = normal_cdf_pdf(x);
            cdf + x * pdf
        },
    })
}

/// `(Φ(x), φ(x))`, the standard normal's distribution and density, with one `exp`. `erf` is Abramowitz and
/// Stegun's 7.1.26 (absolute error below 1.5e-7, float32's resolution near one), whose `e^{−z²}` at `z = x/√2` is
/// the density's `e^{−x²/2}`: libm's scalar `erff` was the largest part of GELU's cost.
fn normal_cdf_pdf(x: f32) -> (f32, f32) {
    const P: f32 = 0.327_591_1;
    const A: [f32; 5] = [0.254_829_6, -0.284_496_74, 1.421_413_7, -1.453_152_1, 1.061_405_4];
    const INV_SQRT_2PI: f32 = 0.398_942_3;
    let e = (-0.5 * x * x).exp();
    let t = 1. / (1. + P * x.abs() * std::f32::consts::FRAC_1_SQRT_2);
    let poly = t * (A[0] + t * (A[1] + t * (A[2] + t * (A[3] + t * A[4]))));
    let erf_abs = 1. - poly * e;
    let erf = if x < 0. { -erf_abs } else { erf_abs };
    (0.5 * (1. + erf), INV_SQRT_2PI * e)
}

/// `max(x, 0)`, with candle's gradient convention (`g` where `x ≥ 0`) so that results do not change from `relu()`;
/// candle's own backward builds a comparison tensor, a type conversion and a product, each a pass over the batch.
/// NaN stays NaN, as in PyTorch (`f32::max` would turn it into 0 and hide a broken network behind finite actions).
pub fn relu(x: &Tensor) -> CResult<Tensor> {
    if !x.device().is_cpu() {
        return composed::relu(x);
    }
    x.contiguous()?.apply_op1(Elementwise {
        name: "relu",
        value: |x: f32| if x.is_nan() { x } else { x.max(0.) },
        slope: |x: f32| if x >= 0. { 1. } else { 0. },
    })
}

/// `x` clamped to `[low, high]`, with the gradient passed where `x` lies inside (candle's convention). NaN stays NaN,
/// as in PyTorch's `clamp`: candle's clamp is `max(min(x, high), low)` in Rust's `f32::max`, which turns NaN into
/// `low`, so a network that went NaN inside (an overflow of finite weights) played a bounded action instead of
/// failing the evaluation.
pub fn clamp(x: &Tensor, low: f64, high: f64) -> CResult<Tensor> {
    if !x.device().is_cpu() {
        return x.clamp(low, high);
    }
    let (lo, hi) = (low as f32, high as f32);
    x.contiguous()?.apply_op1(Elementwise {
        name: "clamp",
        value: move |x: f32| if x.is_nan() { x } else { x.clamp(lo, hi) },
        slope: move |x: f32| if (lo..=hi).contains(&x) { 1. } else { 0. },
    })
}

/// A function applied to each element: `value(x)` forward, `g · slope(x)` backward. Generic over the two functions
/// (not `fn` pointers) so each operation's loops are compiled with its functions inlined: called through a pointer,
/// ReLU's forward was as costly as the matrix products around it in BEAR-Lag's step.
struct Elementwise<V, S> {
    name: &'static str,
    value: V,
    slope: S,
}

impl<V, S> CustomOp1 for Elementwise<V, S>
where
    V: Fn(f32) -> f32 + Send + Sync,
    S: Fn(f32) -> f32 + Send + Sync,
{
    fn name(&self) -> &'static str {
        self.name
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> CResult<(CpuStorage, Shape)> {
        let x = slice(storage, layout, self.name)?;
        Ok((
            CpuStorage::F32(x.iter().map(|&v| (self.value)(v)).collect()),
            layout.shape().clone(),
        ))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> CResult<Option<Tensor>> {
        let values = with_elements(x, self.name, |x| {
            with_elements(grad, self.name, |g| {
                Ok(x.iter()
                    .zip(g)
                    .map(|(&x, &g)| g * (self.slope)(x))
                    .collect::<Vec<f32>>())
            })
        })?;
        Ok(Some(tensor(values, x.shape())?))
    }
}

/// Inverted dropout with a given mask: `x ⊙ keep / (1 − p)` where `keep` is true; the gradient is masked alike.
/// The mask is one byte per element, kept by the operation for its backward pass.
pub fn dropout(x: &Tensor, keep: Vec<bool>, p: f64) -> CResult<Tensor> {
    if keep.len() != x.elem_count() {
        return Err(msg(format!(
            "dropout: {} mask entries for {} elements",
            keep.len(),
            x.elem_count()
        )));
    }
    if !x.device().is_cpu() {
        return composed::dropout(x, &keep, p);
    }
    x.contiguous()?.apply_op1(Dropout {
        keep,
        scale: (1.0 / (1.0 - p)) as f32,
    })
}

struct Dropout {
    keep: Vec<bool>,
    scale: f32,
}

impl Dropout {
    fn apply(&self, x: &[f32]) -> Vec<f32> {
        x.iter()
            .zip(&self.keep)
            .map(|(&v, &keep)| if keep { v * self.scale } else { 0. })
            .collect()
    }
}

impl CustomOp1 for Dropout {
    fn name(&self) -> &'static str {
        "dropout"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> CResult<(CpuStorage, Shape)> {
        let x = slice(storage, layout, "dropout")?;
        Ok((CpuStorage::F32(self.apply(x)), layout.shape().clone()))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> CResult<Option<Tensor>> {
        let values = with_elements(grad, "dropout", |g| Ok(self.apply(g)))?;
        Ok(Some(tensor(values, x.shape())?))
    }
}

/// `nn.LayerNorm` over the last axis (biased variance, `eps` inside the square root), then `· weight + bias`.
pub fn layer_norm(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> CResult<Tensor> {
    if !x.device().is_cpu() {
        return composed::layer_norm(x, weight, bias, eps);
    }
    x.contiguous()?.apply_op3(
        &weight.contiguous()?,
        &bias.contiguous()?,
        LayerNormOp { eps: eps as f32 },
    )
}

struct LayerNormOp {
    eps: f32,
}

/// A row's mean and `1/√(var + eps)`, in the order the primitive form computes them.
fn row_moments(row: &[f32], eps: f32) -> (f32, f32) {
    let n = row.len() as f32;
    let mean = row.iter().sum::<f32>() / n;
    let variance = row.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / n;
    (mean, 1. / (variance + eps).sqrt())
}

impl CustomOp3 for LayerNormOp {
    fn name(&self) -> &'static str {
        "layer-norm"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> CResult<(CpuStorage, Shape)> {
        let (x, w, b) = (
            slice(s1, l1, "layer-norm")?,
            slice(s2, l2, "layer-norm")?,
            slice(s3, l3, "layer-norm")?,
        );
        let n = columns(l1.shape(), "layer-norm", w.len())?;
        columns(l1.shape(), "layer-norm", b.len())?;
        let mut out = vec![0f32; x.len()];
        for (row, out) in x.chunks_exact(n.max(1)).zip(out.chunks_exact_mut(n.max(1))) {
            let (mean, inv_std) = row_moments(row, self.eps);
            for (((o, v), w), b) in out.iter_mut().zip(row).zip(w).zip(b) {
                *o = (v - mean) * inv_std * w + b;
            }
        }
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }

    /// With `x̂ = (x − μ)·r` and `g' = g ⊙ w`: `dx = r·(g' − mean(g') − x̂·mean(g' ⊙ x̂))`, `dw = Σ g ⊙ x̂`,
    /// `db = Σ g` over rows.
    fn bwd(
        &self,
        x: &Tensor,
        weight: &Tensor,
        bias: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> CResult<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let n = weight.elem_count().max(1);
        let (dx, dw, db) = with_elements(x, "layer-norm", |x| {
            with_elements(weight, "layer-norm", |w| {
                with_elements(grad, "layer-norm", |g| {
                    let mut dx = vec![0f32; x.len()];
                    let (mut dw, mut db) = (vec![0f32; n], vec![0f32; n]);
                    let mut normed = vec![0f32; n];
                    for ((row, g), dx) in x.chunks_exact(n).zip(g.chunks_exact(n)).zip(dx.chunks_exact_mut(n)) {
                        let (mean, inv_std) = row_moments(row, self.eps);
                        let (mut mean_g, mut mean_gx) = (0f32, 0f32);
                        for j in 0..n {
                            normed[j] = (row[j] - mean) * inv_std;
                            dw[j] += g[j] * normed[j];
                            db[j] += g[j];
                            let gw = g[j] * w[j];
                            mean_g += gw;
                            mean_gx += gw * normed[j];
                        }
                        mean_g /= n as f32;
                        mean_gx /= n as f32;
                        for j in 0..n {
                            dx[j] = inv_std * (g[j] * w[j] - mean_g - normed[j] * mean_gx);
                        }
                    }
                    Ok((dx, dw, db))
                })
            })
        })?;
        Ok((
            Some(tensor(dx, x.shape())?),
            Some(tensor(dw, weight.shape())?),
            Some(tensor(db, bias.shape())?),
        ))
    }
}

/// Softmax over the last axis of `[..., L, L]` attention scores where query `i` sees keys `0..=i` only: the
/// weights of later keys are zero, exactly as adding a `−∞` causal mask before the softmax makes them.
pub fn causal_softmax(scores: &Tensor) -> CResult<Tensor> {
    let dims = scores.dims();
    if dims.len() < 2 || dims[dims.len() - 1] != dims[dims.len() - 2] {
        return Err(msg(format!("causal-softmax: needs [..., L, L] scores, got {dims:?}")));
    }
    if !scores.device().is_cpu() {
        return composed::causal_softmax(scores);
    }
    scores.contiguous()?.apply_op1(CausalSoftmax)
}

struct CausalSoftmax;

impl CustomOp1 for CausalSoftmax {
    fn name(&self) -> &'static str {
        "causal-softmax"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> CResult<(CpuStorage, Shape)> {
        let x = slice(storage, layout, "causal-softmax")?;
        let l = layout.shape().dims().last().copied().unwrap_or(1).max(1);
        let mut out = vec![0f32; x.len()];
        for (r, (row, out)) in x.chunks_exact(l).zip(out.chunks_exact_mut(l)).enumerate() {
            let seen = r % l + 1;
            let max = row[..seen].iter().copied().fold(f32::NEG_INFINITY, f32::max);
            let mut sum = 0f32;
            for (o, v) in out[..seen].iter_mut().zip(&row[..seen]) {
                *o = (v - max).exp();
                sum += *o;
            }
            for o in &mut out[..seen] {
                *o /= sum;
            }
        }
        Ok((CpuStorage::F32(out), layout.shape().clone()))
    }

    /// `dx = y ⊙ (g − Σ g ⊙ y)` per row (zero at the masked keys, where `y` is zero).
    fn bwd(&self, x: &Tensor, res: &Tensor, grad: &Tensor) -> CResult<Option<Tensor>> {
        let l = x.dims().last().copied().unwrap_or(1).max(1);
        let values = with_elements(res, "causal-softmax", |y| {
            with_elements(grad, "causal-softmax", |g| {
                let mut dx = vec![0f32; y.len()];
                for (r, ((y, g), dx)) in y
                    .chunks_exact(l)
                    .zip(g.chunks_exact(l))
                    .zip(dx.chunks_exact_mut(l))
                    .enumerate()
                {
                    let seen = r % l + 1;
                    let dot: f32 = y[..seen].iter().zip(&g[..seen]).map(|(y, g)| y * g).sum();
                    for ((d, y), g) in dx[..seen].iter_mut().zip(&y[..seen]).zip(&g[..seen]) {
                        *d = y * (g - dot);
                    }
                }
                Ok(dx)
            })
        })?;
        Ok(Some(tensor(values, x.shape())?))
    }
}

/// The operations above as compositions of candle's primitive operations, for devices without the fused kernels:
/// candle's CUDA backend runs each primitive and its autograd differentiates them. Per operation:
/// - bias add: `broadcast_add`;
/// - GELU: candle's `gelu_erf` (its backward is candle's);
/// - ReLU: candle's `relu` (on CUDA, `max(NaN, 0)` is 0, so a NaN hidden unit is not kept there as on the CPU; the
///   evaluator, which acts on the CPU, still refuses non-finite actions);
/// - dropout: a product with the mask, scaled, uploaded as a tensor;
/// - layer norm: mean, centred variance, `sqrt(var + eps)`, then weight and bias;
/// - causal softmax: a `−∞` mask above the diagonal added, then [`composed::softmax`].
pub mod composed {
    use candle_core::Tensor;

    use super::{CResult, msg};

    /// Softmax along `dim`, written with primitive operations so that candle's autograd differentiates it (candle-nn's
    /// fused `softmax_last_dim` has no backward pass). The maximum is subtracted for range and detached: softmax does
    /// not change when a constant is subtracted, so neither does its gradient.
    pub fn softmax(x: &Tensor, dim: usize) -> CResult<Tensor> {
        let shifted = x.broadcast_sub(&x.max_keepdim(dim)?.detach())?;
        let exp = shifted.exp()?;
        exp.broadcast_div(&exp.sum_keepdim(dim)?)
    }

    /// `log(softmax(x))` along `dim`, as `x − max − log Σ exp(x − max)` (finite where softmax underflows).
    pub fn log_softmax(x: &Tensor, dim: usize) -> CResult<Tensor> {
        let shifted = x.broadcast_sub(&x.max_keepdim(dim)?.detach())?;
        let log_sum = shifted.exp()?.sum_keepdim(dim)?.log()?;
        shifted.broadcast_sub(&log_sum)
    }

    pub fn bias_add(y: &Tensor, bias: &Tensor) -> CResult<Tensor> {
        super::columns(y.shape(), "bias-add", bias.elem_count())?;
        y.broadcast_add(bias)
    }

    pub fn gelu_erf(x: &Tensor) -> CResult<Tensor> {
        x.gelu_erf()
    }

    pub fn relu(x: &Tensor) -> CResult<Tensor> {
        x.relu()
    }

    pub fn dropout(x: &Tensor, keep: &[bool], p: f64) -> CResult<Tensor> {
        let scale = (1.0 / (1.0 - p)) as f32;
        let mask: Vec<f32> = keep.iter().map(|&k| if k { scale } else { 0. }).collect();
        x.mul(&Tensor::from_vec(mask, x.shape(), x.device())?)
    }

    pub fn layer_norm(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> CResult<Tensor> {
        let last = x
            .rank()
            .checked_sub(1)
            .ok_or_else(|| msg("layer-norm: needs an axis".into()))?;
        let mean = x.mean_keepdim(last)?;
        let centred = x.broadcast_sub(&mean)?;
        let variance = centred.sqr()?.mean_keepdim(last)?;
        let normed = centred.broadcast_div(&variance.affine(1.0, eps)?.sqrt()?)?;
        normed.broadcast_mul(weight)?.broadcast_add(bias)
    }

    pub fn causal_softmax(scores: &Tensor) -> CResult<Tensor> {
        let dims = scores.dims();
        if dims.len() < 2 || dims[dims.len() - 1] != dims[dims.len() - 2] {
            return Err(msg(format!("causal-softmax: needs [..., L, L] scores, got {dims:?}")));
        }
        let l = dims[dims.len() - 1];
        let mask: Vec<f32> = (0..l)
            .flat_map(|i| (0..l).map(move |j| if j <= i { 0.0 } else { f32::NEG_INFINITY }))
            .collect();
        let mask = Tensor::from_vec(mask, (l, l), scores.device())?;
        softmax(&scores.broadcast_add(&mask)?, dims.len() - 1).map_err(|e| msg(format!("causal-softmax: {e}")))
    }
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Var};

    use super::*;
    use crate::noise::Noise;

    fn random(shape: &[usize], seed: u64) -> Var {
        let mut noise = Noise::seeded(seed);
        let n = shape.iter().product();
        let values: Vec<f32> = (0..n).map(|_| noise.normal() as f32).collect();
        Var::from_vec(values, shape, &Device::Cpu).unwrap()
    }

    fn values(t: &Tensor) -> Vec<f32> {
        t.flatten_all().unwrap().to_vec1().unwrap()
    }

    fn close(a: &[f32], b: &[f32], tolerance: f32, what: &str) {
        assert_eq!(a.len(), b.len(), "{what}");
        for (i, (a, b)) in a.iter().zip(b).enumerate() {
            assert!((a - b).abs() <= tolerance * (1. + b.abs()), "{what}[{i}]: {a} vs {b}");
        }
    }

    /// Forward values and the gradients of `Σ w ⊙ f(inputs)` agree between the fused and the primitive form.
    fn same_as_primitive(
        inputs: &[Var],
        fused: impl Fn(&[Tensor]) -> Tensor,
        primitive: impl Fn(&[Tensor]) -> Tensor,
        what: &str,
    ) {
        let tensors: Vec<Tensor> = inputs.iter().map(|v| v.as_tensor().clone()).collect();
        let (a, b) = (fused(&tensors), primitive(&tensors));
        close(&values(&a), &values(&b), 1e-5, what);
        let weights = random(a.dims(), 99);
        let grads = |t: &Tensor| {
            t.mul(weights.as_tensor())
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap()
        };
        let (grads_a, grads_b) = (grads(&a), grads(&b));
        for (k, input) in tensors.iter().enumerate() {
            close(
                &values(grads_a.get(input).unwrap()),
                &values(grads_b.get(input).unwrap()),
                1e-4,
                &format!("{what}: gradient of input {k}"),
            );
        }
    }

    #[test]
    fn bias_add_and_its_gradient_match_a_broadcast_add() {
        let (y, b) = (random(&[2, 5, 3], 1), random(&[3], 2));
        same_as_primitive(
            &[y, b],
            |t| bias_add(&t[0], &t[1]).unwrap(),
            |t| composed::bias_add(&t[0], &t[1]).unwrap(),
            "bias-add",
        );
        let err = bias_add(&random(&[2, 4], 3), &random(&[3], 4)).unwrap_err().to_string();
        assert!(err.contains("last axis 4 against a parameter of 3"), "{err}");
    }

    #[test]
    fn gelu_and_its_gradient_match_candles_gelu_erf() {
        // Spread over GELU's curved region and its tails.
        let x = Var::from_vec(
            (0..64).map(|i| (i as f32 - 32.) / 5.).collect::<Vec<f32>>(),
            (8, 8),
            &Device::Cpu,
        )
        .unwrap();
        same_as_primitive(
            &[x],
            |t| gelu_erf(&t[0]).unwrap(),
            |t| composed::gelu_erf(&t[0]).unwrap(),
            "gelu",
        );
    }

    #[test]
    fn relu_and_its_gradient_match_candles() {
        let mut x = random(&[4, 5], 16)
            .as_tensor()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        x[3] = 0.0;
        let x = Var::from_vec(x, (4, 5), &Device::Cpu).unwrap();
        same_as_primitive(
            &[x],
            |t| relu(&t[0]).unwrap(),
            |t| composed::relu(&t[0]).unwrap(),
            "relu",
        );
    }

    #[test]
    fn clamp_keeps_nan_as_pytorch_does_and_matches_candles_otherwise() {
        let x = Tensor::new(&[f32::NAN, -3.0, 0.5, 2.0, f32::INFINITY], &Device::Cpu).unwrap();
        let y = clamp(&x, -1.0, 1.0).unwrap().to_vec1::<f32>().unwrap();
        assert!(y[0].is_nan(), "{y:?}");
        assert_eq!(&y[1..], &[-1.0, 0.5, 1.0, 1.0]);
        let x = random(&[4, 5], 21);
        same_as_primitive(
            &[x],
            |t| clamp(&t[0], -0.3, 0.4).unwrap(),
            |t| t[0].clamp(-0.3, 0.4).unwrap(),
            "clamp",
        );
    }

    #[test]
    fn relu_keeps_nan_as_pytorch_does() {
        let x = Tensor::new(&[f32::NAN, -1.0, 2.0], &Device::Cpu).unwrap();
        let y = relu(&x).unwrap().to_vec1::<f32>().unwrap();
        assert!(y[0].is_nan());
        assert_eq!(&y[1..], &[0.0, 2.0]);
    }

    #[test]
    fn dropout_scales_what_it_keeps_and_masks_its_gradient_alike() {
        let x = random(&[2, 3], 14);
        let keep = vec![true, false, true, true, false, true];
        same_as_primitive(
            &[x],
            |t| dropout(&t[0], keep.clone(), 0.2).unwrap(),
            |t| composed::dropout(&t[0], &keep, 0.2).unwrap(),
            "dropout",
        );
        let kept = composed::dropout(
            &Tensor::ones((2, 3), candle_core::DType::F32, &Device::Cpu).unwrap(),
            &keep,
            0.2,
        )
        .unwrap();
        assert_eq!(values(&kept), [1.25, 0., 1.25, 1.25, 0., 1.25]);
        let err = dropout(&random(&[2, 3], 15), vec![true; 5], 0.2)
            .unwrap_err()
            .to_string();
        assert!(err.contains("5 mask entries for 6 elements"), "{err}");
    }

    #[test]
    fn layer_norm_and_its_gradients_match_the_primitive_form() {
        let (x, w, b) = (random(&[3, 4, 6], 5), random(&[6], 6), random(&[6], 7));
        same_as_primitive(
            &[x, w, b],
            |t| layer_norm(&t[0], &t[1], &t[2], 1e-5).unwrap(),
            |t| composed::layer_norm(&t[0], &t[1], &t[2], 1e-5).unwrap(),
            "layer-norm",
        );
    }

    #[test]
    fn causal_softmax_matches_a_masked_softmax_and_its_gradient() {
        // The composed form is the masked softmax: weights above the diagonal are exactly zero.
        let l = 5;
        let composed = composed::causal_softmax(random(&[1, l, l], 17).as_tensor()).unwrap();
        let rows = composed.squeeze(0).unwrap().to_vec2::<f32>().unwrap();
        for (i, row) in rows.iter().enumerate() {
            assert!(row[i + 1..].iter().all(|&w| w == 0.), "row {i}: {row:?}");
            assert!((row.iter().sum::<f32>() - 1.).abs() < 1e-6, "row {i}: {row:?}");
        }
        same_as_primitive(
            &[random(&[2, 3, l, l], 8)],
            |t| causal_softmax(&t[0]).unwrap(),
            |t| composed::causal_softmax(&t[0]).unwrap(),
            "causal-softmax",
        );
        let err = causal_softmax(&random(&[2, 3, 4], 9)).unwrap_err().to_string();
        assert!(err.contains("needs [..., L, L]"), "{err}");
    }

    /// The fused gradients against central differences, independently of autograd.
    #[test]
    fn fused_gradients_match_finite_differences() {
        let x = random(&[2, 4, 4], 10);
        let (w, b) = (random(&[4], 11), random(&[4], 12));
        let weights = random(&[2, 4, 4], 13);
        let loss = |x: &Tensor| -> f32 {
            let y = layer_norm(x, w.as_tensor(), b.as_tensor(), 1e-5).unwrap();
            let y = causal_softmax(&gelu_erf(&y).unwrap()).unwrap();
            y.mul(weights.as_tensor())
                .unwrap()
                .sum_all()
                .unwrap()
                .to_scalar()
                .unwrap()
        };
        let y = layer_norm(x.as_tensor(), w.as_tensor(), b.as_tensor(), 1e-5).unwrap();
        let y = causal_softmax(&gelu_erf(&y).unwrap()).unwrap();
        let grads = y
            .mul(weights.as_tensor())
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let analytic = values(grads.get(x.as_tensor()).unwrap());
        let base = values(x.as_tensor());
        let h = 1e-2f32;
        for k in 0..base.len() {
            let at = |d: f32| {
                let mut v = base.clone();
                v[k] += d;
                loss(&Tensor::from_vec(v, (2, 4, 4), &Device::Cpu).unwrap())
            };
            let numeric = (at(h) - at(-h)) / (2. * h);
            assert!(
                (numeric - analytic[k]).abs() < 3e-3,
                "{k}: {numeric} vs {}",
                analytic[k]
            );
        }
    }
}
