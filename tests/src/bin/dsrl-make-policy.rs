//! `dsrl-make-policy`: writes a freshly initialised, seeded policy checkpoint for a task, in any architecture of the
//! format, for end-to-end tests (scoring, parity with the Python reference) of the architectures this project does
//! not train. Its scores mean nothing; its actions exercise every part of the network.

use std::path::PathBuf;

use clap::{Parser, ValueEnum};
use dsrl_policy::caps::{CapsNetworks, CapsShape};
use dsrl_policy::cdt::{Cdt, CdtShape};
use dsrl_policy::checkpoint::{self, Architecture, Conditioning, DiffusionSampler, PolicyConfig, ReturnTarget};
use dsrl_policy::diffusion::{CandidateChoice, DiffusionShape, NoiseNet};
use dsrl_policy::latent::LatentSource;
use dsrl_policy::mlp::{Activation, Mlp};
use dsrl_policy::noise::Noise;
use dsrl_policy::offline::Ensemble;
use dsrl_suite::catalog::Catalog;

#[derive(Debug, Clone, Copy, ValueEnum)]
enum Arch {
    /// OSRL's BCQ-Lag actor: hidden [64, 64] (tanh), decoder [64, 64], latent 2 x act_dim, phi 0.05.
    BcqActor,
    /// A CDT (embedding 32, 2 layers, 4 heads, K = 10) conditioned on (max reward, threshold) per threshold.
    Cdt,
    /// An MLP actor [64, 64] that reads the cost threshold after the observation (target_cost conditioning).
    TargetCostMlp,
    /// CAPS: 3 heads on a [64, 64] trunk, critic pairs [64, 64]; cost_scale 0.01 and a shifted cost critic put the
    /// budget at the size of the critic's predictions, so the switch takes both of its branches.
    Caps,
    /// A diffusion policy (FISOR's form): time features 8, conditioning [16, 16], 2 residual blocks of 16 with
    /// LayerNorm; 3 DDPM steps over 4 candidates, the lowest of a [32, 32] feasibility critic pair played.
    Diffusion,
    /// A latent policy (LSPC's form): safety encoder [32, 32] over a latent of 4 bounded at 0.6, decoder [32, 32].
    LatentPolicy,
}

#[derive(Debug, Parser)]
struct Args {
    #[arg(long)]
    task: String,
    #[arg(long, value_enum)]
    arch: Arch,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output folder (policy.json + policy.safetensors).
    out: PathBuf,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let catalog = Catalog::embedded()?;
    let task = catalog.get(&args.task)?;
    let (obs_dim, act_dim) = (task.obs_dim as usize, task.act_dim as usize);
    let mut noise = Noise::seeded(args.seed);
    let (architecture, conditioning, vars) = match args.arch {
        Arch::BcqActor => {
            let latent_dim = 2 * act_dim;
            let pi = Mlp::orthogonal(
                "actor.pi",
                &[obs_dim + act_dim, 64, 64, act_dim],
                Activation::Tanh,
                1.0,
                1.0,
                &mut noise,
            )?;
            let decoder = Mlp::orthogonal(
                "vae.decoder",
                &[obs_dim + latent_dim, 64, 64, act_dim],
                Activation::Relu,
                2f64.sqrt(),
                1.0,
                &mut noise,
            )?;
            let architecture = Architecture::BcqActor {
                hidden_sizes: vec![64, 64],
                activation: Activation::Tanh,
                decoder_hidden_sizes: vec![64, 64],
                latent_dim,
                phi: 0.05,
                max_action: 1.0,
            };
            let vars: Vec<_> = pi.named_vars().into_iter().chain(decoder.named_vars()).collect();
            (architecture, Conditioning::Unconditioned, vars)
        }
        Arch::Cdt => {
            let shape = CdtShape {
                obs_dim,
                act_dim,
                embedding_dim: 32,
                num_layers: 2,
                num_heads: 4,
                seq_len: 10,
                episode_len: task.max_episode_steps as usize,
            };
            let model = Cdt::new(shape, true, &mut noise)?;
            let architecture = Architecture::Cdt {
                embedding_dim: 32,
                num_layers: 2,
                num_heads: 4,
                seq_len: 10,
                episode_len: shape.episode_len,
                max_action: 1.0,
                reward_scale: 0.1,
                cost_scale: 1.0,
                cost_transform: true,
            };
            let targets = task
                .cost_thresholds
                .iter()
                .map(|&k| ReturnTarget {
                    cost_threshold: k,
                    reward_return: task.max_episode_reward,
                    cost_return: k,
                })
                .collect();
            (architecture, Conditioning::ReturnsToGo { targets }, model.named_vars())
        }
        Arch::TargetCostMlp => {
            let net = Mlp::orthogonal(
                "actor.net",
                &[obs_dim + 1, 64, 64, act_dim],
                Activation::Relu,
                2f64.sqrt(),
                1.0,
                &mut noise,
            )?;
            let architecture = Architecture::MlpActor {
                hidden_sizes: vec![64, 64],
                activation: Activation::Relu,
                max_action: 1.0,
            };
            (architecture, Conditioning::TargetCost, net.named_vars())
        }
        Arch::Caps => {
            let shape = CapsShape {
                obs_dim,
                act_dim,
                hidden_sizes: vec![64, 64],
                num_heads: 3,
            };
            let nets = CapsNetworks::new(shape, &mut noise)?;
            // A fresh cost critic predicts ~−0.04 everywhere, which every limit admits; shifted to ~0.17 its
            // predictions straddle the per-step limits of a budget of 20 at cost_scale 0.01 (0.127 at the first
            // step), so some steps have heads that fit and some none.
            for net in &nets.cost_q.nets {
                for (name, var) in net.named_vars() {
                    if name.ends_with(".2.bias") {
                        var.set(&var.as_tensor().affine(1.0, -0.21)?)?;
                    }
                }
            }
            let architecture = Architecture::Caps {
                hidden_sizes: vec![64, 64],
                num_heads: 3,
                max_action: 1.0,
                gamma: 0.99,
                episode_len: task.max_episode_steps as usize,
                cost_scale: 0.01,
            };
            (architecture, Conditioning::CostBudget, nets.named_vars())
        }
        Arch::Diffusion => {
            let shape = DiffusionShape {
                obs_dim,
                act_dim,
                time_dim: 8,
                cond_sizes: vec![16, 16],
                hidden_dim: 16,
                num_blocks: 2,
                layer_norm: true,
            };
            let net = NoiseNet::new(shape, &mut noise)?;
            let critic = Ensemble::new("cost_q", obs_dim + act_dim, &[32, 32], 2, &mut noise)?;
            let architecture = Architecture::Diffusion {
                time_dim: 8,
                cond_sizes: vec![16, 16],
                hidden_dim: 16,
                num_blocks: 2,
                layer_norm: true,
                critic_hidden_sizes: vec![32, 32],
                critic_members: 2,
                max_action: 1.0,
                sampler: DiffusionSampler::Ddpm {
                    steps: 3,
                    beta_min: 0.1,
                    beta_max: 10.0,
                    clip: true,
                    temperature: 1.0,
                    candidates: 4,
                    choice: CandidateChoice::MinCostQ,
                },
            };
            let vars = net.named_vars("actor").into_iter().chain(critic.named_vars()).collect();
            (architecture, Conditioning::Unconditioned, vars)
        }
        Arch::LatentPolicy => {
            let latent_dim = 4;
            let mlp = |prefix: &str, sizes: &[usize], noise: &mut Noise| {
                Mlp::pytorch_default(prefix, sizes, Activation::Relu, noise)
            };
            let trunk = mlp("safety.trunk", &[obs_dim, 32, 32], &mut noise)?;
            let mu = mlp("safety.mu", &[32, latent_dim], &mut noise)?;
            let log_std = mlp("safety.log_std", &[32, latent_dim], &mut noise)?;
            let decoder = mlp("vae.decoder", &[obs_dim + latent_dim, 32, 32, act_dim], &mut noise)?;
            let architecture = Architecture::LatentPolicy {
                hidden_sizes: vec![32, 32],
                decoder_hidden_sizes: vec![32, 32],
                latent_dim,
                max_latent: 0.6,
                latent: LatentSource::SafetyEncoder,
                max_action: 1.0,
            };
            let vars = [trunk, mu, log_std, decoder].iter().flat_map(Mlp::named_vars).collect();
            (architecture, Conditioning::Unconditioned, vars)
        }
    };
    let config = PolicyConfig {
        format: checkpoint::FORMAT.into(),
        task: task.id.to_string(),
        obs_dim,
        act_dim,
        architecture,
        observation_normalization: None,
        conditioning,
        training: Some(serde_json::json!({"fixture": "dsrl-make-policy", "seed": args.seed})),
    };
    checkpoint::write(&args.out, &config, &dsrl_policy::tensors_of(vars))?;
    Ok(())
}
