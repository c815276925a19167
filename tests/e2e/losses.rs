//! FISOR's and LSPC's losses against a second computation: the learners (freshly initialised, small, on rows of the
//! BallRun starter) compute their weights, targets and losses on a fixed batch with fixed draws, write them with
//! every network and input, and `tests/parity/fisor_lspc_losses.py` computes the same formulas again in NumPy from
//! the papers' code (FISOR's `fisor.py`, LSPC's `lspc_iql.py`) and compares. JAX's and PyTorch's random numbers
//! cannot be matched, so the draws (step indices, noise, latents) are inputs here, not regenerated.

use std::collections::HashMap;
use std::process::Command;

use dsrl_policy::Tensor;
use dsrl_train::fisor::{FisorLearner, FisorSettings};
use dsrl_train::lspc::{LspcLearner, LspcSettings};

const ROWS: usize = 64;

fn tensor(values: Vec<f32>, shape: &[usize]) -> Tensor {
    Tensor::from_vec(values, shape, &dsrl_policy::Device::Cpu).unwrap()
}

#[test]
fn fisor_and_lspc_losses_equal_a_numpy_computation_of_their_formulas() {
    let data = dsrl_train::Demonstrations::read(&crate::leaderboard::starter()).unwrap();
    let (o, a) = (data.obs_dim, data.act_dim);
    // Every 17th row: a spread of states, costly steps among them.
    let pick = |values: &[f32], width: usize| -> Vec<f32> {
        (0..ROWS)
            .flat_map(|i| values[i * 17 * width..(i * 17 + 1) * width].to_vec())
            .collect()
    };
    let obs = tensor(pick(&data.observations, o), &[ROWS, o]);
    let act = tensor(pick(&data.actions, a), &[ROWS, a]);
    let cost = tensor(pick(&data.costs, 1), &[ROWS]);
    let done = tensor(pick(&data.dones, 1), &[ROWS]);
    let mut noise = dsrl_policy::noise::Noise::seeded(9);
    let steps: Vec<usize> = (0..ROWS).map(|_| (noise.next_u64() % 5) as usize).collect();
    let eps = tensor(noise.normals_f32(ROWS * a), &[ROWS, a]);
    let latents = tensor(noise.normals_f32(ROWS * 8), &[ROWS, 8]);
    let next_vc = tensor(noise.normals_f32(ROWS), &[ROWS]).affine(10.0, 0.0).unwrap();

    let fisor_settings = FisorSettings {
        time_dim: 16,
        cond_sizes: vec![32, 32],
        hidden_dim: 32,
        num_blocks: 2,
        dropout: 0.0,
        critic_hidden_sizes: vec![32, 32],
        seed: 4,
        ..FisorSettings::default()
    };
    let mut fisor = FisorLearner::new(fisor_settings.clone(), &data).unwrap();
    // The weights from the networks (their target copies are still the same weights). A fresh feasibility pair
    // answers about the same everywhere: its output biases are moved to the middle of the batch's values, so the
    // batch has infeasible rows, feasible safe ones and feasible unsafe ones (weight 0), which the script counts.
    // The middle between the two central values, not the median itself: a shift by the median puts that row's value
    // at 0, on the boundary the weights branch on, where f32 here and f64 in NumPy may fall on different sides
    // (they did, on a CPU whose matrix kernels round differently).
    let input = dsrl_policy::offline::concat(&obs, &act).unwrap();
    let median = |t: &Tensor| {
        let mut v = t.to_vec1::<f32>().unwrap();
        v.sort_by(f32::total_cmp);
        (v[v.len() / 2 - 1] + v[v.len() / 2]) / 2.0
    };
    let shift = |vars: Vec<(String, dsrl_policy::Var)>, by: f32| {
        for (name, var) in vars {
            if name.ends_with(".2.bias") {
                var.set(&var.as_tensor().affine(1.0, f64::from(-by)).unwrap()).unwrap();
            }
        }
    };
    let qc = |fisor: &FisorLearner| dsrl_policy::offline::Ensemble::max(&fisor.cost_q.values(&input).unwrap()).unwrap();
    let vc = |fisor: &FisorLearner| fisor.cost_v.forward(&obs).unwrap().squeeze(1).unwrap();
    shift(fisor.cost_q.named_vars(), median(&qc(&fisor)));
    shift(fisor.cost_v.named_vars(), median(&vc(&fisor)));
    // No row may sit near the boundary, or the comparison would test rounding, not the formula.
    for (what, values) in [("Q_h", qc(&fisor)), ("V_h", vc(&fisor))] {
        let nearest = values
            .to_vec1::<f32>()
            .unwrap()
            .iter()
            .map(|x| x.abs())
            .fold(f32::INFINITY, f32::min);
        assert!(nearest > 1e-5, "a row's {what} is {nearest} from the boundary");
    }
    let weights = {
        let q = dsrl_policy::offline::Ensemble::min(&fisor.reward_q.values(&input).unwrap()).unwrap();
        let v = fisor.reward_v.forward(&obs).unwrap().squeeze(1).unwrap();
        FisorLearner::weights(&fisor_settings, &q, &v, &qc(&fisor), &vc(&fisor)).unwrap()
    };
    let actor_loss = fisor.actor_loss(&obs, &act, &weights, &steps, &eps).unwrap();
    let c = FisorLearner::recode_cost(&cost, 25.0).unwrap();
    let mask = done.affine(-1.0, 1.0).unwrap();
    let target = FisorLearner::reachability_target(&c, &next_vc, &mask, 0.99).unwrap();

    let lspc_settings = LspcSettings {
        hidden: 32,
        latent_dim: 8,
        max_latent: 0.6,
        seed: 5,
        ..LspcSettings::default()
    };
    let lspc = LspcLearner::new(lspc_settings, &data).unwrap();
    let lspc_weights = tensor((0..ROWS).map(|i| 0.5 + (i % 7) as f32).collect(), &[ROWS]);
    let vae_loss = lspc.vae_loss(&obs, &act, &latents, &lspc_weights).unwrap();
    let safety_loss = lspc.safety_loss(&obs, &act, &latents, &lspc_weights).unwrap();

    let mut out: HashMap<String, Tensor> = HashMap::new();
    let networks = fisor
        .actor
        .named_vars("actor")
        .into_iter()
        .chain(fisor.reward_q.named_vars())
        .chain(fisor.cost_q.named_vars())
        .chain(fisor.reward_v.named_vars())
        .chain(fisor.cost_v.named_vars())
        .chain(lspc.vae.named_vars())
        .chain(lspc.safety.named_vars());
    for (name, var) in networks {
        out.insert(format!("net/{name}"), var.as_tensor().clone());
    }
    let steps_f32 = tensor(steps.iter().map(|&t| t as f32).collect(), &[ROWS]);
    for (name, t) in [
        ("in/obs", obs),
        ("in/act", act),
        ("in/cost", cost),
        ("in/done", done),
        ("in/steps", steps_f32),
        ("in/eps", eps),
        ("in/latents", latents),
        ("in/next_vc", next_vc),
        ("in/lspc_weights", lspc_weights),
        ("out/fisor_weights", weights),
        ("out/fisor_actor_loss", actor_loss.reshape(1).unwrap()),
        ("out/fisor_cost", c),
        ("out/fisor_target", target),
        ("out/lspc_vae_loss", vae_loss.reshape(1).unwrap()),
        ("out/lspc_safety_loss", safety_loss.reshape(1).unwrap()),
    ] {
        out.insert(name.into(), t);
    }
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("losses.safetensors");
    dsrl_policy::candle_save(&out, &file).unwrap();
    let check = Command::new(dsrl_e2e::repo_root().join(".venv-sim/bin/python"))
        .arg(dsrl_e2e::repo_root().join("tests/parity/fisor_lspc_losses.py"))
        .arg(&file)
        .args([
            "--fisor",
            &serde_json::json!({"time_dim": 16, "cond": 2, "blocks": 2, "steps": 5}).to_string(),
        ])
        .args(["--max-latent", "0.6", "--vae-beta", "0.5"])
        .output()
        .unwrap();
    let report = String::from_utf8_lossy(&check.stdout);
    eprintln!("{report}");
    assert!(
        check.status.success(),
        "{report}{}",
        String::from_utf8_lossy(&check.stderr)
    );
    // Both sides of the feasibility boundary were exercised.
    assert!(
        report.contains("infeasible rows: ") && !report.contains("infeasible rows: 0 "),
        "{report}"
    );
}
