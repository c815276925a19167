//! What OSRL's Q-learning and DICE baselines share (spec 5.3): ensembles of Q (or V) networks, target copies moved
//! by soft updates, the PID Lagrangian controller that weighs the cost critic, and the conversion of an episode
//! cost threshold into a per-step Q-value threshold. Each algorithm's module builds on these.

use candle_core::{Device, Tensor, Var};

use crate::Result;
use crate::mlp::{Activation, Mlp, layer_sizes};
use crate::noise::Noise;

/// OSRL's `LagrangianPIDController` (spec 5.3), called once per training step with the batch's cost-Q values:
/// `e = mean(qc − thres)`, `d = relu(e − e_old)`, `I = relu(I + e)`, `e_old = e`,
/// `λ = relu(Kp·relu(e) + Ki·I + Kd·d)`. It differs from FSRL's multiplier (the expert's) in the `relu(e)` of the
/// proportional term and in taking Q values, not episode costs.
#[derive(Debug, Clone, PartialEq)]
pub struct PidLagrangian {
    pub kp: f64,
    pub ki: f64,
    pub kd: f64,
    pub threshold: f64,
    pub error_old: f64,
    pub error_integral: f64,
}

impl PidLagrangian {
    /// OSRL's gains for BCQ-L and BEAR-L: (0.1, 0.003, 0.001).
    pub fn osrl(threshold: f64) -> PidLagrangian {
        PidLagrangian::new(0.1, 0.003, 0.001, threshold)
    }

    pub fn new(kp: f64, ki: f64, kd: f64, threshold: f64) -> PidLagrangian {
        PidLagrangian {
            kp,
            ki,
            kd,
            threshold,
            error_old: 0.0,
            error_integral: 0.0,
        }
    }

    /// λ for this step from the batch's cost-Q values.
    pub fn control(&mut self, qc: &[f32]) -> f64 {
        if qc.is_empty() {
            return 0.0;
        }
        let error = qc.iter().map(|&q| f64::from(q) - self.threshold).sum::<f64>() / qc.len() as f64;
        let derivative = (error - self.error_old).max(0.0);
        self.error_integral = (self.error_integral + error).max(0.0);
        self.error_old = error;
        (self.kp * error.max(0.0) + self.ki * self.error_integral + self.kd * derivative).max(0.0)
    }
}

/// OSRL's per-step cost-Q threshold for an episode cost threshold `kappa`: the discounted sum of a constant cost
/// spread evenly over an episode of `episode_len` steps, `κ·(1 − γ^L)/(1 − γ)/L`.
pub fn qc_threshold(kappa: f64, gamma: f64, episode_len: usize) -> f64 {
    let l = episode_len as f64;
    kappa * (1.0 - gamma.powf(l)) / (1.0 - gamma) / l
}

/// OSRL's `EnsembleQCritic`: `num` networks `[in, hidden.., 1]` (ReLU), each reading `[obs, act]` (or only `obs`
/// for a V network, as COptiDICE's ν and χ). Named `<prefix>.<i>.<layer>`.
pub struct Ensemble {
    pub nets: Vec<Mlp>,
}

impl Ensemble {
    /// Initialised as PyTorch's `nn.Linear` default (uniform in ±1/√fan_in for weights and biases), which OSRL's
    /// critics keep.
    pub fn new(prefix: &str, input_dim: usize, hidden: &[usize], num: usize, noise: &mut Noise) -> Result<Ensemble> {
        let sizes = layer_sizes(input_dim, hidden, 1);
        let nets = (0..num)
            .map(|i| Mlp::pytorch_default(&format!("{prefix}.{i}"), &sizes, Activation::Relu, noise))
            .collect::<Result<_>>()?;
        Ok(Ensemble { nets })
    }

    /// Each network's values for the rows of `input` (`[batch, in]`), as `[batch]` tensors.
    pub fn values(&self, input: &Tensor) -> Result<Vec<Tensor>> {
        self.nets.iter().map(|n| Ok(n.forward(input)?.squeeze(1)?)).collect()
    }

    /// The element-wise minimum over the ensemble (OSRL's `predict`).
    pub fn min(values: &[Tensor]) -> Result<Tensor> {
        let mut out = values[0].clone();
        for v in &values[1..] {
            out = out.minimum(v)?;
        }
        Ok(out)
    }

    /// The element-wise maximum over the ensemble (the pessimistic cost estimate: FISOR's feasibility, LSPC's cost).
    pub fn max(values: &[Tensor]) -> Result<Tensor> {
        let mut out = values[0].clone();
        for v in &values[1..] {
            out = out.maximum(v)?;
        }
        Ok(out)
    }

    /// The mean over the ensemble of each network's mean squared error: [`Ensemble::loss`] over the count (the IQL
    /// family's critic loss: CAPS, FISOR, LSPC).
    pub fn mean_loss(values: &[Tensor], target: &Tensor) -> Result<Tensor> {
        Ok(Ensemble::loss(values, target)?.affine(1.0 / values.len() as f64, 0.0)?)
    }

    /// `Σ_q mean((q − target)²)` (OSRL's critic loss).
    pub fn loss(values: &[Tensor], target: &Tensor) -> Result<Tensor> {
        let mut total = values[0].sub(target)?.sqr()?.mean_all()?;
        for v in &values[1..] {
            total = total.add(&v.sub(target)?.sqr()?.mean_all()?)?;
        }
        Ok(total)
    }

    pub fn named_vars(&self) -> Vec<(String, Var)> {
        self.nets.iter().flat_map(Mlp::named_vars).collect()
    }

    /// A copy with the same weights, whose variables are its own (a target network).
    pub fn copy(&self) -> Result<Ensemble> {
        Ok(Ensemble {
            nets: self.nets.iter().map(Mlp::copy).collect::<Result<_>>()?,
        })
    }

    pub fn to_device(self, device: &Device) -> Result<Ensemble> {
        Ok(Ensemble {
            nets: self
                .nets
                .into_iter()
                .map(|n| n.to_device(device))
                .collect::<Result<_>>()?,
        })
    }
}

/// OSRL's `EnsembleDoubleQCritic` (BCQ-L, BEAR-L): two ensembles `<prefix>.q1`, `<prefix>.q2` of `num` networks
/// each (so `2·num` networks) read `[obs, act]`; each ensemble answers its element-wise minimum.
pub struct DoubleCritic {
    pub q1: Ensemble,
    pub q2: Ensemble,
}

impl DoubleCritic {
    pub fn new(prefix: &str, input_dim: usize, hidden: &[usize], num: usize, noise: &mut Noise) -> Result<Self> {
        Ok(DoubleCritic {
            q1: Ensemble::new(&format!("{prefix}.q1"), input_dim, hidden, num, noise)?,
            q2: Ensemble::new(&format!("{prefix}.q2"), input_dim, hidden, num, noise)?,
        })
    }

    pub fn to_device(self, device: &Device) -> Result<DoubleCritic> {
        Ok(DoubleCritic {
            q1: self.q1.to_device(device)?,
            q2: self.q2.to_device(device)?,
        })
    }

    /// Every network's values (the loss sums over all of them), and the two ensembles' minima.
    pub fn predict(&self, input: &Tensor) -> Result<(Vec<Tensor>, Tensor, Tensor)> {
        let (v1, v2) = (self.q1.values(input)?, self.q2.values(input)?);
        let (m1, m2) = (Ensemble::min(&v1)?, Ensemble::min(&v2)?);
        Ok((v1.into_iter().chain(v2).collect(), m1, m2))
    }

    /// BCQ-L's and BEAR-L's target value over `n` sampled actions per state: per sample
    /// `λ·min(q1, q2) + (1 − λ)·max(q1, q2)`, then the maximum over each state's `n` samples (rows `i·n .. i·n + n`
    /// belong to state `i`). Returns `[rows / n]`.
    pub fn soft_clipped_max(q1: &Tensor, q2: &Tensor, lmbda: f64, n: usize) -> Result<Tensor> {
        let q = q1
            .minimum(q2)?
            .affine(lmbda, 0.0)?
            .add(&q1.maximum(q2)?.affine(1.0 - lmbda, 0.0)?)?;
        let rows = q.dim(0)?;
        Ok(q.reshape((rows / n, n))?.max(1)?)
    }

    pub fn named_vars(&self) -> Vec<(String, Var)> {
        self.q1.named_vars().into_iter().chain(self.q2.named_vars()).collect()
    }

    /// A copy with the same weights and its own variables (a target network).
    pub fn copy(&self) -> Result<Self> {
        Ok(DoubleCritic {
            q1: self.q1.copy()?,
            q2: self.q2.copy()?,
        })
    }
}

/// Repeats each row of `x` `n` times in place (`torch.repeat_interleave(x, n, 0)`): row `i` becomes rows
/// `i·n .. i·n + n`.
pub fn repeat_rows(x: &Tensor, n: usize) -> Result<Tensor> {
    let rows = x.dim(0)? as u32;
    let index: Vec<u32> = (0..rows).flat_map(|i| std::iter::repeat_n(i, n)).collect();
    let index = Tensor::from_vec(index, rows as usize * n, x.device())?;
    Ok(x.index_select(&index, 0)?)
}

/// `log(1 + eˣ)`, written to stay finite for large |x|: `max(x, 0) + log(1 + e^{−|x|})`.
pub fn softplus(x: &Tensor) -> Result<Tensor> {
    Ok(x.relu()?.add(&x.abs()?.neg()?.exp()?.affine(1.0, 1.0)?.log()?)?)
}

/// The `q`-quantile of `values` with linear interpolation between order statistics (NumPy's and PyTorch's default).
pub fn quantile(values: &[f32], q: f64) -> f32 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f32::total_cmp);
    let position = q * (sorted.len() - 1) as f64;
    let (lo, hi) = (position.floor() as usize, position.ceil() as usize);
    let weight = (position - lo as f64) as f32;
    sorted[lo] + (sorted[hi] - sorted[lo]) * weight
}

/// Polyak averaging of a target network towards its source: `target ← τ·source + (1 − τ)·target`, variable by
/// variable in order (both lists come from the same architecture's `named_vars`).
pub fn soft_update(target: &[(String, Var)], source: &[(String, Var)], tau: f64) -> Result<()> {
    assert_eq!(
        target.len(),
        source.len(),
        "soft update between different architectures"
    );
    for ((tn, t), (sn, s)) in target.iter().zip(source) {
        debug_assert_eq!(tn.rsplit('.').next(), sn.rsplit('.').next());
        let moved = s
            .as_tensor()
            .affine(tau, 0.0)?
            .add(&t.as_tensor().affine(1.0 - tau, 0.0)?)?;
        t.set(&moved)?;
    }
    Ok(())
}

/// `[a | b]` along the last axis (the critics read `[obs, act]`).
pub fn concat(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    Ok(Tensor::cat(&[a, b], 1)?)
}

/// A `[rows, cols]` tensor from row-major values.
pub fn rows(values: Vec<f32>, rows: usize, cols: usize) -> Result<Tensor> {
    Ok(Tensor::from_vec(values, (rows, cols), &Device::Cpu)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pid_controller_follows_osrl_by_hand() {
        let mut pid = PidLagrangian::new(0.1, 0.003, 0.001, 3.0);
        // Q values averaging 5 over a threshold of 3: e = 2, d = 2, I = 2.
        let l1 = pid.control(&[4.0, 6.0]);
        assert!((l1 - (0.1 * 2.0 + 0.003 * 2.0 + 0.001 * 2.0)).abs() < 1e-12, "{l1}");
        // The same error: d = 0, I = 4.
        let l2 = pid.control(&[5.0]);
        assert!((l2 - (0.1 * 2.0 + 0.003 * 4.0)).abs() < 1e-12, "{l2}");
        // Below the threshold: the proportional term is clipped at 0 (relu(e)), the integral shrinks to 1.
        let l3 = pid.control(&[0.0]);
        assert!((l3 - 0.003).abs() < 1e-12, "{l3}");
        assert_eq!(pid.error_integral, 1.0);
        // Far below: λ is 0 and the integral never goes negative.
        assert_eq!(pid.control(&[-100.0]), 0.0);
        assert_eq!(pid.error_integral, 0.0);
    }

    #[test]
    fn quantiles_interpolate_as_numpy_and_torch() {
        // numpy.quantile([1, 2, 3, 4], 0.75) = 3.25; [5, 1, 3] at 0.75 = 4.0; a single value is itself.
        assert_eq!(quantile(&[4.0, 1.0, 3.0, 2.0], 0.75), 3.25);
        assert_eq!(quantile(&[5.0, 1.0, 3.0], 0.75), 4.0);
        assert_eq!(quantile(&[7.0], 0.75), 7.0);
    }

    #[test]
    fn softplus_is_finite_and_exact_at_the_extremes() {
        let x = Tensor::new(&[-100.0f32, -1.0, 0.0, 2.0, 100.0], &Device::Cpu).unwrap();
        let y: Vec<f32> = softplus(&x).unwrap().to_vec1().unwrap();
        let want = [
            0.0f32,
            (1.0 + (-1.0f32).exp()).ln(),
            2.0f32.ln(),
            (1.0 + 2.0f32.exp()).ln(),
            100.0,
        ];
        for (a, b) in y.iter().zip(&want) {
            assert!((a - b).abs() < 1e-6, "{y:?}");
        }
    }

    #[test]
    fn repeated_rows_and_the_soft_clipped_maximum_follow_osrl_by_hand() {
        let x = rows(vec![1.0, 2.0, 3.0, 4.0], 2, 2).unwrap();
        let r: Vec<Vec<f32>> = repeat_rows(&x, 3).unwrap().to_vec2().unwrap();
        assert_eq!(
            r,
            vec![
                vec![1.0, 2.0],
                vec![1.0, 2.0],
                vec![1.0, 2.0],
                vec![3.0, 4.0],
                vec![3.0, 4.0],
                vec![3.0, 4.0]
            ]
        );
        // Two states, two samples each: 0.75·min + 0.25·max per sample, then the max per state.
        let q1 = Tensor::new(&[1.0f32, 4.0, -2.0, 0.0], &Device::Cpu).unwrap();
        let q2 = Tensor::new(&[3.0f32, 2.0, -1.0, -4.0], &Device::Cpu).unwrap();
        let v: Vec<f32> = DoubleCritic::soft_clipped_max(&q1, &q2, 0.75, 2)
            .unwrap()
            .to_vec1()
            .unwrap();
        // state 0: samples 0.75·1 + 0.25·3 = 1.5 and 0.75·2 + 0.25·4 = 2.5; state 1: −1.75 and −3.
        assert_eq!(v, vec![2.5, -1.75]);
    }

    #[test]
    fn the_cost_threshold_conversion_matches_the_spec_example() {
        // κ = 10, γ = 0.99, L = 300 → 3.1699 (spec 5.3).
        let q = qc_threshold(10.0, 0.99, 300);
        assert!((q - 3.1699).abs() < 1e-4, "{q}");
        // γ → 1 would be κ/L per step summed over L steps: the threshold tends to κ.
        assert!((qc_threshold(10.0, 0.999_999, 100) - 10.0).abs() < 1e-3);
    }

    #[test]
    fn soft_updates_move_a_target_by_tau() {
        let mut noise = Noise::seeded(1);
        let source = Ensemble::new("q", 3, &[4], 2, &mut noise).unwrap();
        let target = Ensemble::new("t", 3, &[4], 2, &mut noise).unwrap();
        let before: Vec<Vec<f32>> = target
            .named_vars()
            .iter()
            .map(|(_, v)| v.as_tensor().flatten_all().unwrap().to_vec1().unwrap())
            .collect();
        soft_update(&target.named_vars(), &source.named_vars(), 0.005).unwrap();
        for ((_, t), ((_, s), old)) in target.named_vars().iter().zip(source.named_vars().iter().zip(&before)) {
            let t: Vec<f32> = t.as_tensor().flatten_all().unwrap().to_vec1().unwrap();
            let s: Vec<f32> = s.as_tensor().flatten_all().unwrap().to_vec1().unwrap();
            for ((t, s), o) in t.iter().zip(&s).zip(old) {
                assert!((t - (0.005 * s + 0.995 * o)).abs() < 1e-6);
            }
        }
        // A copy is independent of its source.
        let copy = source.copy().unwrap();
        soft_update(&source.named_vars(), &target.named_vars(), 1.0).unwrap();
        let a: Vec<f32> = copy.nets[0].named_vars()[0]
            .1
            .as_tensor()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let b: Vec<f32> = source.nets[0].named_vars()[0]
            .1
            .as_tensor()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        assert_ne!(a, b);
    }

    #[test]
    fn the_ensemble_loss_sums_each_networks_mse_and_its_gradient_matches_finite_differences() {
        let mut noise = Noise::seeded(7);
        let critic = Ensemble::new("q", 3, &[5], 2, &mut noise).unwrap();
        let input = rows(noise.normals_f32(12), 4, 3).unwrap();
        let target = Tensor::from_vec(noise.normals_f32(4), 4, &Device::Cpu).unwrap();
        let values = critic.values(&input).unwrap();
        let loss = Ensemble::loss(&values, &target).unwrap();
        let by_hand: f32 = values
            .iter()
            .map(|v| {
                let v: Vec<f32> = v.to_vec1().unwrap();
                let t: Vec<f32> = target.to_vec1().unwrap();
                v.iter().zip(&t).map(|(a, b)| (a - b).powi(2)).sum::<f32>() / 4.0
            })
            .sum();
        assert!((loss.to_scalar::<f32>().unwrap() - by_hand).abs() < 1e-5);
        // The minimum is element-wise.
        let min: Vec<f32> = Ensemble::min(&values).unwrap().to_vec1().unwrap();
        let (a, b): (Vec<f32>, Vec<f32>) = (values[0].to_vec1().unwrap(), values[1].to_vec1().unwrap());
        assert!(min.iter().zip(a.iter().zip(&b)).all(|(m, (a, b))| *m == a.min(*b)));
        // Autograd against central differences on one weight of the second network.
        let grads = loss.backward().unwrap();
        let (_, w) = &critic.nets[1].named_vars()[0];
        let analytic: Vec<f32> = grads
            .get(w.as_tensor())
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let original: Vec<f32> = w.as_tensor().flatten_all().unwrap().to_vec1().unwrap();
        let h = 1e-2f32;
        let loss_at = |k: usize, delta: f32| {
            let mut moved = original.clone();
            moved[k] += delta;
            w.set(&Tensor::from_vec(moved, w.as_tensor().dims(), &Device::Cpu).unwrap())
                .unwrap();
            let l = Ensemble::loss(&critic.values(&input).unwrap(), &target).unwrap();
            l.to_scalar::<f32>().unwrap()
        };
        for k in [0, 4, 9] {
            let numeric = (loss_at(k, h) - loss_at(k, -h)) / (2.0 * h);
            assert!(
                (numeric - analytic[k]).abs() < 2e-2 * (1.0 + analytic[k].abs()),
                "{k}: {numeric} vs {}",
                analytic[k]
            );
        }
    }
}
