//! OSRL's conditional VAE of the behaviour policy (spec 5.3), shared by BCQ-L, BEAR-L and CPQ:
//!
//! ```text
//! encoder: [obs, act] → hidden → hidden (ReLU) → mean, log σ (clamped to [−4, 15])
//! z = mean + σ·ε                      ε ~ N(0, 1)
//! decoder: [obs, z] → hidden → hidden (ReLU) → max_action · tanh(·)
//! loss = mean((decoder(obs, z) − act)²) + β · KL,   KL = −½ · mean(1 + log σ² − mean² − σ²)
//! ```
//!
//! Tensors: `vae.encoder.<i>`, `vae.mean.0`, `vae.log_std.0` (training only) and `vae.decoder.<i>`, the names the
//! evaluator's BCQ actor reads ([`crate::bcq`]), so a trained decoder is submitted as is.

use candle_core::{Tensor, Var};

use crate::Result;
use crate::mlp::{Activation, Mlp, layer_sizes};
use crate::noise::Noise;

/// OSRL's clamp of the encoder's log σ.
pub const LOG_STD_RANGE: (f64, f64) = (-4.0, 15.0);

pub struct Vae {
    /// The shared trunk of the encoder (ReLU after each layer, as OSRL's e1, e2).
    pub encoder: Mlp,
    pub mean: Mlp,
    pub log_std: Mlp,
    pub decoder: Mlp,
    pub latent_dim: usize,
    pub max_action: f64,
}

/// One pass of the VAE over a batch, with what its loss and the algorithms need.
pub struct VaeOutput {
    pub reconstruction: Tensor,
    pub mean: Tensor,
    pub std: Tensor,
}

impl Vae {
    /// OSRL's layout: `hidden` units in both encoder layers and both decoder layers, PyTorch-default initialised.
    pub fn new(
        obs_dim: usize,
        act_dim: usize,
        hidden: usize,
        latent_dim: usize,
        max_action: f64,
        noise: &mut Noise,
    ) -> Result<Vae> {
        // The encoder trunk ends in a ReLU too: an MLP `[in, h, h]` plus the activation applied by `encode`.
        let encoder = Mlp::pytorch_default(
            "vae.encoder",
            &[obs_dim + act_dim, hidden, hidden],
            Activation::Relu,
            noise,
        )?;
        let mean = Mlp::pytorch_default("vae.mean", &[hidden, latent_dim], Activation::Relu, noise)?;
        let log_std = Mlp::pytorch_default("vae.log_std", &[hidden, latent_dim], Activation::Relu, noise)?;
        let decoder = Mlp::pytorch_default(
            "vae.decoder",
            &layer_sizes(obs_dim + latent_dim, &[hidden, hidden], act_dim),
            Activation::Relu,
            noise,
        )?;
        Ok(Vae {
            encoder,
            mean,
            log_std,
            decoder,
            latent_dim,
            max_action,
        })
    }

    /// The latent distribution of `[obs, act]` rows: (mean, σ).
    pub fn encode(&self, obs: &Tensor, act: &Tensor) -> Result<(Tensor, Tensor)> {
        let h = crate::fused::relu(&self.encoder.forward(&Tensor::cat(&[obs, act], 1)?)?)?;
        let mean = self.mean.forward(&h)?;
        let log_std = self.log_std.forward(&h)?.clamp(LOG_STD_RANGE.0, LOG_STD_RANGE.1)?;
        Ok((mean, log_std.exp()?))
    }

    /// `max_action · tanh(decoder([obs, z]))`.
    pub fn decode(&self, obs: &Tensor, z: &Tensor) -> Result<Tensor> {
        Ok(self
            .decoder
            .forward(&Tensor::cat(&[obs, z], 1)?)?
            .tanh()?
            .affine(self.max_action, 0.0)?)
    }

    /// Encode, draw `z = mean + σ·ε` with `epsilon` (`[batch, latent]` standard normal draws), decode.
    pub fn forward(&self, obs: &Tensor, act: &Tensor, epsilon: &Tensor) -> Result<VaeOutput> {
        let (mean, std) = self.encode(obs, act)?;
        let z = mean.add(&std.mul(epsilon)?)?;
        Ok(VaeOutput {
            reconstruction: self.decode(obs, &z)?,
            mean,
            std,
        })
    }

    /// `mean((reconstruction − act)²) + β · KL` (OSRL's `vae_loss`), with the two parts: (total, reconstruction,
    /// KL).
    pub fn loss(out: &VaeOutput, act: &Tensor, beta: f64) -> Result<(Tensor, Tensor, Tensor)> {
        let reconstruction = out.reconstruction.sub(act)?.sqr()?.mean_all()?;
        // −½ · mean(1 + log σ² − μ² − σ²)
        let log_var = out.std.sqr()?.log()?;
        let kl = log_var
            .affine(1.0, 1.0)?
            .sub(&out.mean.sqr()?)?
            .sub(&out.std.sqr()?)?
            .mean_all()?
            .affine(-0.5, 0.0)?;
        let total = reconstruction.add(&kl.affine(beta, 0.0)?)?;
        Ok((total, reconstruction, kl))
    }

    pub fn named_vars(&self) -> Vec<(String, Var)> {
        [&self.encoder, &self.mean, &self.log_std, &self.decoder]
            .into_iter()
            .flat_map(Mlp::named_vars)
            .collect()
    }

    pub fn to_device(self, device: &candle_core::Device) -> Result<Vae> {
        Ok(Vae {
            encoder: self.encoder.to_device(device)?,
            mean: self.mean.to_device(device)?,
            log_std: self.log_std.to_device(device)?,
            decoder: self.decoder.to_device(device)?,
            ..self
        })
    }
}

#[cfg(test)]
mod tests {
    use candle_core::Device;

    use super::*;

    #[test]
    fn the_vae_loss_is_the_reconstruction_error_plus_beta_kl_worked_by_hand() {
        let mut noise = Noise::seeded(3);
        let vae = Vae::new(3, 2, 8, 4, 1.0, &mut noise).unwrap();
        let obs = Tensor::from_vec(noise.normals_f32(6), (2, 3), &Device::Cpu).unwrap();
        let act = Tensor::from_vec(vec![0.5f32, -0.5, 0.1, 0.2], (2, 2), &Device::Cpu).unwrap();
        let eps = Tensor::from_vec(noise.normals_f32(8), (2, 4), &Device::Cpu).unwrap();
        let out = vae.forward(&obs, &act, &eps).unwrap();
        let (total, rec, kl) = Vae::loss(&out, &act, 0.5).unwrap();
        let r: Vec<f32> = out.reconstruction.flatten_all().unwrap().to_vec1().unwrap();
        let a = [0.5f32, -0.5, 0.1, 0.2];
        let rec_hand = r.iter().zip(a).map(|(x, y)| (x - y).powi(2)).sum::<f32>() / 4.0;
        assert!((rec.to_scalar::<f32>().unwrap() - rec_hand).abs() < 1e-6);
        let m: Vec<f32> = out.mean.flatten_all().unwrap().to_vec1().unwrap();
        let s: Vec<f32> = out.std.flatten_all().unwrap().to_vec1().unwrap();
        let kl_hand = -0.5
            * m.iter()
                .zip(&s)
                .map(|(m, s)| 1.0 + (s * s).ln() - m * m - s * s)
                .sum::<f32>()
            / 8.0;
        assert!((kl.to_scalar::<f32>().unwrap() - kl_hand).abs() < 1e-5);
        assert!((total.to_scalar::<f32>().unwrap() - (rec_hand + 0.5 * kl_hand)).abs() < 1e-5);
        // A standard-normal posterior costs no KL.
        let zero = VaeOutput {
            reconstruction: out.reconstruction.clone(),
            mean: Tensor::zeros((2, 4), candle_core::DType::F32, &Device::Cpu).unwrap(),
            std: Tensor::ones((2, 4), candle_core::DType::F32, &Device::Cpu).unwrap(),
        };
        assert!(Vae::loss(&zero, &act, 0.5).unwrap().2.to_scalar::<f32>().unwrap().abs() < 1e-7);
        // Decoded actions stay inside the action bound.
        assert!(r.iter().all(|x| x.abs() <= 1.0));
    }

    #[test]
    fn a_trained_decoder_is_what_the_evaluators_bcq_actor_reads() {
        let mut noise = Noise::seeded(4);
        let vae = Vae::new(7, 2, 16, 4, 1.0, &mut noise).unwrap();
        let names: Vec<String> = vae.named_vars().into_iter().map(|(n, _)| n).collect();
        for name in [
            "vae.decoder.0.weight",
            "vae.decoder.2.bias",
            "vae.encoder.1.weight",
            "vae.mean.0.weight",
        ] {
            assert!(names.contains(&name.to_owned()), "{names:?}");
        }
        assert!(
            names
                .iter()
                .filter(|n| !n.starts_with("vae.decoder."))
                .all(|n| crate::bcq::TRAINING_ONLY.iter().any(|p| n.starts_with(p))),
            "everything but the decoder is training-only for the evaluator"
        );
    }
}
