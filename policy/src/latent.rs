//! LSPC's policy (Koirala & Fleming, ICLR 2025; its code's `lspc_iql.py`): a conditional VAE's decoder turns a
//! latent into an action, and the latent comes either from the safety encoder, a Gaussian policy over the latent
//! space trained by advantage-weighted regression (LSPC-O), or from the VAE's prior clamped to a box (LSPC-S):
//!
//! ```text
//! encoder: z = max_latent · tanh(μ(s) + σ(s)·ε)        μ, log σ heads on a ReLU trunk; log σ clamped to [−10, 2]
//! prior:   z = clamp(ε, ±max_latent)
//! action   = max_action · tanh(decoder([s, z]))         ε ~ N(0, I), drawn per step
//! ```
//!
//! LSPC samples at evaluation in both modes; here every draw comes from a generator seeded with the episode's seed,
//! one per environment slot, so a score is reproducible. Tensors: `safety.trunk.<i>` (ReLU after every layer),
//! `safety.mu.0`, `safety.log_std.0`, `vae.decoder.<i>` (ReLU between); the VAE's encoder (`vae.encoder.<i>`,
//! `vae.mean.0`, `vae.log_std.0`) is only used in training, and so is the safety encoder in prior mode.

use candle_core::{Device, Tensor};

use crate::Result;
pub use crate::checkpoint::LatentSource;
use crate::layers::Weights;
use crate::mlp::{Activation, Mlp, layer_sizes};
use crate::noise::Noise;

/// LSPC's clamp on the safety encoder's log σ.
pub const LOG_STD_RANGE: (f64, f64) = (-10.0, 2.0);

pub const TRAINING_ONLY: [&str; 3] = ["vae.encoder.", "vae.mean.", "vae.log_std."];
/// In prior mode the safety encoder only trains as well.
pub const TRAINING_ONLY_PRIOR: [&str; 4] = ["vae.encoder.", "vae.mean.", "vae.log_std.", "safety."];

/// The declared sizes of a latent policy.
#[derive(Debug, Clone, PartialEq)]
pub struct LatentShape {
    pub obs_dim: usize,
    pub act_dim: usize,
    pub latent_dim: usize,
    pub hidden_sizes: Vec<usize>,
    pub decoder_hidden_sizes: Vec<usize>,
}

/// The safety encoder: a ReLU trunk with `μ` and `log σ` heads over the latent space.
pub struct SafetyEncoder {
    pub trunk: Mlp,
    pub mu: Mlp,
    pub log_std: Mlp,
}

impl SafetyEncoder {
    /// `(μ, log σ)` for `obs`, log σ clamped to [`LOG_STD_RANGE`].
    pub fn forward(&self, obs: &Tensor) -> Result<(Tensor, Tensor)> {
        let h = self.trunk.forward(obs)?.relu()?;
        let log_std = self
            .log_std
            .forward(&h)?
            .clamp(LOG_STD_RANGE.0 as f32, LOG_STD_RANGE.1 as f32)?;
        Ok((self.mu.forward(&h)?, log_std))
    }

    /// The squashed latent `max_latent · tanh(μ + σ·ε)` for given standard normal draws `eps`.
    pub fn latent(&self, obs: &Tensor, eps: &Tensor, max_latent: f64) -> Result<Tensor> {
        let (mu, log_std) = self.forward(obs)?;
        Ok(mu.add(&log_std.exp()?.mul(eps)?)?.tanh()?.affine(max_latent, 0.0)?)
    }

    pub fn named_vars(&self) -> Vec<(String, candle_core::Var)> {
        let mut out = self.trunk.named_vars();
        out.extend(self.mu.named_vars());
        out.extend(self.log_std.named_vars());
        out
    }
}

/// A latent policy at evaluation.
pub struct LatentPolicy {
    pub shape: LatentShape,
    /// Present in `safety_encoder` mode.
    pub encoder: Option<SafetyEncoder>,
    pub decoder: Mlp,
    pub source: LatentSource,
    pub max_latent: f64,
    pub max_action: f64,
}

impl LatentPolicy {
    /// The safety encoder's tensors for `shape`.
    pub fn encoder_from_weights(shape: &LatentShape, w: &mut Weights) -> Result<SafetyEncoder> {
        let mut trunk_sizes = vec![shape.obs_dim];
        trunk_sizes.extend(&shape.hidden_sizes);
        let last = *shape.hidden_sizes.last().unwrap_or(&shape.obs_dim);
        Ok(SafetyEncoder {
            trunk: w.mlp("safety.trunk", &trunk_sizes, Activation::Relu)?,
            mu: w.mlp("safety.mu", &[last, shape.latent_dim], Activation::Relu)?,
            log_std: w.mlp("safety.log_std", &[last, shape.latent_dim], Activation::Relu)?,
        })
    }

    pub fn from_weights(
        shape: LatentShape,
        source: LatentSource,
        max_latent: f64,
        max_action: f64,
        w: &mut Weights,
    ) -> Result<LatentPolicy> {
        let encoder = match source {
            LatentSource::SafetyEncoder => Some(Self::encoder_from_weights(&shape, w)?),
            LatentSource::Prior => None,
        };
        let decoder = w.mlp(
            "vae.decoder",
            &layer_sizes(
                shape.obs_dim + shape.latent_dim,
                &shape.decoder_hidden_sizes,
                shape.act_dim,
            ),
            Activation::Relu,
        )?;
        Ok(LatentPolicy {
            shape,
            encoder,
            decoder,
            source,
            max_latent,
            max_action,
        })
    }

    /// `max_action · tanh(decoder([obs, z]))`.
    pub fn decode(decoder: &Mlp, obs: &Tensor, z: &Tensor, max_action: f64) -> Result<Tensor> {
        Ok(decoder
            .forward(&Tensor::cat(&[obs, z], 1)?)?
            .tanh()?
            .affine(max_action, 0.0)?)
    }

    /// Actions `[states, act]` for `obs`, slot `i`'s latent draw from `generators[i]`.
    pub fn act(&self, obs: &Tensor, generators: &mut [&mut Noise]) -> Result<Vec<f32>> {
        let eps = crate::diffusion::normal_rows(generators, 1, self.shape.latent_dim, &Device::Cpu)?;
        let z = match &self.encoder {
            Some(encoder) => encoder.latent(obs, &eps, self.max_latent)?,
            None => eps.clamp(-self.max_latent as f32, self.max_latent as f32)?,
        };
        Ok(Self::decode(&self.decoder, obs, &z, self.max_action)?
            .flatten_all()?
            .to_vec1::<f32>()?)
    }
}
