//! Policy networks in candle, shared by the expert trainer (`dsrl-admin collect`), the reference learners and the evaluator, with
//! their checkpoint format: `policy.safetensors` (the weights) beside `policy.json` (what the weights are).
//!
//! Everything random takes an explicit seed ([`noise::Noise`]): weight initialisation, exploration noise and
//! minibatch order, so a training run is a function of its recipe. Candle's matrix products are pinned to one
//! thread by the binaries (two threads were slower on this machine, and one thread keeps sums in a fixed order).

pub mod acting;
pub mod adam;
pub mod bcq;
pub mod caps;
pub mod cdt;
pub mod checkpoint;
pub mod diffusion;
pub mod fused;
pub mod gaussian;
pub mod latent;
pub mod layers;
pub mod mlp;
pub mod noise;
pub mod offline;
pub mod squashed;
pub mod vae;

pub use acting::{Policy, Rollout};
pub use candle_core::{DType, Device, Tensor, Var};

#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    #[error("tensor computation failed: {0}")]
    Candle(#[from] candle_core::Error),
    #[error("{0}")]
    Format(String),
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
}

pub type Result<T> = std::result::Result<T, PolicyError>;

/// The current values of named variables, as a checkpoint or a training state stores them.
pub fn tensors_of(vars: impl IntoIterator<Item = (String, Var)>) -> Vec<(String, Tensor)> {
    vars.into_iter().map(|(n, v)| (n, v.as_tensor().clone())).collect()
}

/// `var` on `device`: the same variable when it is there already, else a new variable holding a copy (training
/// builds its networks on the CPU, from the seeded initialisation, and then moves them to the device it trains on).
pub fn var_on(var: &Var, device: &Device) -> Result<Var> {
    if var.device().same_device(device) {
        return Ok(var.clone());
    }
    Ok(Var::from_tensor(&var.as_tensor().to_device(device)?)?)
}

/// Writes named tensors as one safetensors file (through a temporary name and a rename).
pub fn candle_save(tensors: &std::collections::HashMap<String, Tensor>, path: &std::path::Path) -> Result<()> {
    let part = path.with_extension("safetensors.part");
    let on_cpu = tensors
        .iter()
        .map(|(name, t)| Ok((name.clone(), t.to_device(&Device::Cpu)?)))
        .collect::<Result<std::collections::HashMap<_, _>>>()?;
    candle_core::safetensors::save(&on_cpu, &part)?;
    std::fs::rename(&part, path).map_err(|source| PolicyError::Io {
        path: path.display().to_string(),
        source,
    })
}

/// Pins candle's CPU kernels to one thread unless the caller chose otherwise (`RAYON_NUM_THREADS`).
///
/// # Safety
/// Sets an environment variable: call before any other thread exists (first thing in `main`).
pub unsafe fn pin_candle_threads() {
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        // SAFETY: the caller guarantees no other thread reads the environment concurrently.
        unsafe { std::env::set_var("RAYON_NUM_THREADS", "1") };
    }
}

/// The matrix kernels candle's gemm runs on this CPU: `AVX2` (with FMA), or the architecture's `baseline`. Kernels
/// that add in another order round differently, so they decide the bits of a trained network, an expert's dataset
/// and a played episode. gemm is built without its AVX-512 kernels (the workspace's Cargo.toml), so an AVX-512
/// machine runs the AVX2 ones too; records made before that say `AVX-512` where they ran on one.
pub fn matrix_kernels() -> &'static str {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("fma") {
            return "AVX2";
        }
    }
    "baseline"
}
