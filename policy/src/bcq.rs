//! The BCQ-style actor of OSRL's BCQ-Lag (spec 5.3, 5.6): a VAE decoder proposes an action for the observation and a
//! latent draw, and a perturbation network nudges it by at most `phi · max_action`:
//!
//! ```text
//! proposal = max_action · tanh(decoder([obs, z]))            z ~ N(0, 1) clipped to ±0.5
//! action   = clamp(proposal + phi · max_action · tanh(pi([obs, proposal])), ±max_action)
//! ```
//!
//! Tensors: `actor.pi.<i>` (the perturbation MLP, the declared activation between layers) and `vae.decoder.<i>`
//! (OSRL's `d1`, `d2`, `d3`, ReLU between). The VAE's encoder (`vae.encoder.<i>`, `vae.mean`, `vae.log_std`) is
//! only used in training; it is accepted when present. At evaluation the latent is drawn like OSRL's `decode`, from
//! a generator seeded per episode, so a score is reproducible.

use candle_core::{Device, Tensor};

use crate::Result;
use crate::layers::Weights;
use crate::mlp::{Activation, Mlp, layer_sizes};
use crate::noise::Noise;

/// OSRL's latent clip in `VAE.decode`.
pub const LATENT_CLIP: f64 = 0.5;

pub const TRAINING_ONLY: [&str; 3] = ["vae.encoder.", "vae.mean.", "vae.log_std."];

pub struct BcqActor {
    pub perturbation: Mlp,
    pub decoder: Mlp,
    pub latent_dim: usize,
    pub phi: f64,
    pub max_action: f64,
}

/// The declared sizes of a BCQ actor.
pub struct BcqShape<'a> {
    pub input_dim: usize,
    pub act_dim: usize,
    pub latent_dim: usize,
    pub hidden_sizes: &'a [usize],
    pub decoder_hidden_sizes: &'a [usize],
}

impl BcqActor {
    pub fn from_weights(
        shape: &BcqShape,
        activation: Activation,
        phi: f64,
        max_action: f64,
        w: &mut Weights,
    ) -> Result<BcqActor> {
        let perturbation = w.mlp(
            "actor.pi",
            &layer_sizes(shape.input_dim + shape.act_dim, shape.hidden_sizes, shape.act_dim),
            activation,
        )?;
        let decoder = w.mlp(
            "vae.decoder",
            &layer_sizes(
                shape.input_dim + shape.latent_dim,
                shape.decoder_hidden_sizes,
                shape.act_dim,
            ),
            Activation::Relu,
        )?;
        Ok(BcqActor {
            perturbation,
            decoder,
            latent_dim: shape.latent_dim,
            phi,
            max_action,
        })
    }

    /// Actions for `obs [B, in]` and latents `z [B, latent]` (unclipped; see [`BcqActor::latents`]).
    pub fn act(&self, obs: &Tensor, z: &Tensor) -> Result<Tensor> {
        let proposal = self
            .decoder
            .forward(&Tensor::cat(&[obs, z], 1)?)?
            .tanh()?
            .affine(self.max_action, 0.0)?;
        let nudge = self
            .perturbation
            .forward(&Tensor::cat(&[obs, &proposal], 1)?)?
            .tanh()?
            .affine(self.phi * self.max_action, 0.0)?;
        // NaN kept: a network that overflowed inside must fail the evaluation, not play the bound.
        Ok(crate::fused::clamp(
            &proposal.add(&nudge)?,
            -self.max_action,
            self.max_action,
        )?)
    }

    /// One latent row per generator: `latent_dim` standard normal draws, each clipped to ±0.5 (OSRL `decode`).
    pub fn latents(&self, generators: &mut [&mut Noise]) -> Result<Tensor> {
        let values: Vec<f32> = generators
            .iter_mut()
            .flat_map(|g| {
                (0..self.latent_dim)
                    .map(|_| g.normal().clamp(-LATENT_CLIP, LATENT_CLIP) as f32)
                    .collect::<Vec<_>>()
            })
            .collect();
        Ok(Tensor::from_vec(
            values,
            (generators.len(), self.latent_dim),
            &Device::Cpu,
        )?)
    }

    pub fn to_device(self, device: &Device) -> Result<BcqActor> {
        Ok(BcqActor {
            perturbation: self.perturbation.to_device(device)?,
            decoder: self.decoder.to_device(device)?,
            ..self
        })
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use super::*;

    /// Finite weights whose products overflow: the perturbation's hidden units are all +∞ (ReLU keeps them), and its
    /// output subtracts two of them, ∞ − ∞ = NaN. The clamp to the action bound must keep the NaN (PyTorch does), so
    /// the evaluator refuses the action instead of playing the bound.
    #[test]
    fn a_nan_inside_the_network_reaches_the_action_through_the_clamp() {
        let t = |v: Vec<f32>, shape: &[usize]| Tensor::from_vec(v, shape, &Device::Cpu).unwrap();
        let mut tensors: HashMap<String, Tensor> = HashMap::new();
        tensors.insert("actor.pi.0.weight".into(), t(vec![3e38; 4 * 5], &[4, 5]));
        tensors.insert("actor.pi.0.bias".into(), t(vec![0.0; 4], &[4]));
        let mut out = vec![0.0f32; 2 * 4];
        out[0] = 1.0;
        out[1] = -1.0;
        tensors.insert("actor.pi.1.weight".into(), t(out, &[2, 4]));
        tensors.insert("actor.pi.1.bias".into(), t(vec![0.0; 2], &[2]));
        tensors.insert("vae.decoder.0.weight".into(), t(vec![0.01; 4 * 7], &[4, 7]));
        tensors.insert("vae.decoder.0.bias".into(), t(vec![0.0; 4], &[4]));
        tensors.insert("vae.decoder.1.weight".into(), t(vec![0.01; 2 * 4], &[2, 4]));
        tensors.insert("vae.decoder.1.bias".into(), t(vec![0.0; 2], &[2]));
        let shape = BcqShape {
            input_dim: 3,
            act_dim: 2,
            latent_dim: 4,
            hidden_sizes: &[4],
            decoder_hidden_sizes: &[4],
        };
        let actor = BcqActor::from_weights(&shape, Activation::Relu, 0.05, 1.0, &mut Weights::new(&tensors)).unwrap();
        let obs = t(vec![1.0, 1.0, 1.0], &[1, 3]);
        let z = t(vec![0.0; 4], &[1, 4]);
        let action = actor
            .act(&obs, &z)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert!(action[0].is_nan(), "the NaN was clamped away: {action:?}");
    }

    #[test]
    fn the_action_is_the_decoded_proposal_plus_a_bounded_perturbation() {
        let mut noise = Noise::seeded(6);
        let pi = Mlp::orthogonal("actor.pi", &[3 + 2, 8, 2], Activation::Tanh, 1.0, 1.0, &mut noise).unwrap();
        let decoder =
            Mlp::orthogonal("vae.decoder", &[3 + 4, 8, 8, 2], Activation::Relu, 1.0, 1.0, &mut noise).unwrap();
        let encoder = Mlp::orthogonal("vae.encoder", &[5, 8], Activation::Relu, 1.0, 1.0, &mut noise).unwrap();
        let tensors: HashMap<String, Tensor> = crate::tensors_of(
            pi.named_vars()
                .into_iter()
                .chain(decoder.named_vars())
                .chain(encoder.named_vars()),
        )
        .into_iter()
        .collect();
        let shape = BcqShape {
            input_dim: 3,
            act_dim: 2,
            latent_dim: 4,
            hidden_sizes: &[8],
            decoder_hidden_sizes: &[8, 8],
        };
        let mut w = Weights::new(&tensors);
        let actor = BcqActor::from_weights(&shape, Activation::Tanh, 0.05, 1.0, &mut w).unwrap();
        w.finish(&TRAINING_ONLY).unwrap();

        let obs = Tensor::from_vec(vec![0.2f32, -0.3, 0.9], (1, 3), &Device::Cpu).unwrap();
        let mut g = Noise::seeded(11);
        let z = actor.latents(&mut [&mut g]).unwrap();
        let zs = z.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert!(zs.iter().all(|v| v.abs() <= 0.5));
        let got = actor
            .act(&obs, &z)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let proposal = decoder
            .forward(&Tensor::cat(&[&obs, &z], 1).unwrap())
            .unwrap()
            .tanh()
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        for (a, p) in got.iter().zip(&proposal) {
            assert!(
                (a - p).abs() <= 0.05 + 1e-6 && a.abs() <= 1.0,
                "{got:?} vs {proposal:?}"
            );
        }
        // The same generator seed, the same latent and action.
        let again = actor.latents(&mut [&mut Noise::seeded(11)]).unwrap();
        assert_eq!(again.flatten_all().unwrap().to_vec1::<f32>().unwrap(), zs);

        // Declared sizes the weights do not have are refused.
        let wrong = BcqShape { latent_dim: 3, ..shape };
        let err = BcqActor::from_weights(&wrong, Activation::Tanh, 0.05, 1.0, &mut Weights::new(&tensors))
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("vae.decoder has layer sizes [7, 8, 8, 2]"), "{err}");
    }
}
