//! The architectures with state, conditioning or several passes per action (the BCQ actor, the CDT, an MLP
//! conditioned on the target cost, CAPS switching on its remaining budget, a diffusion sampler over candidate
//! actions, a latent policy), as seeded, freshly initialised checkpoints from `dsrl-make-policy`: each plays on the real simulator
//! through `dsrl-admin evaluate` and agrees episode by episode with `tests/parity/evaluate_in_python.py`, which
//! implements every architecture again in NumPy (the CDT unbatched and unpadded, as OSRL's rollout feeds it; the
//! BCQ latents from its own SplitMix64).

use std::path::Path;
use std::process::{Command, Stdio};

const TASK: &str = "OfflineBallRun-v0";

fn evaluate(dir: &Path, extra: &[&str]) -> serde_json::Value {
    let out = Command::new(dsrl_e2e::bin("dsrl-admin"))
        .args(["evaluate", "--workers", "1", "--json"])
        .args(extra)
        .arg(dir)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap()
}

fn python_reference(dir: &Path, cost_threshold: &str) -> serde_json::Value {
    let out = Command::new(dsrl_e2e::repo_root().join(".venv-sim/bin/python"))
        .arg(dsrl_e2e::repo_root().join("tests/parity/evaluate_in_python.py"))
        .arg(dir)
        .args([
            "--sim-id",
            "SafetyBallRun-v0",
            "--episodes",
            "3",
            "--cost-threshold",
            cost_threshold,
        ])
        .stderr(Stdio::inherit())
        .output()
        .unwrap();
    assert!(out.status.success(), "the Python reference failed");
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn stateful_conditioned_and_multi_pass_policies_play_as_the_python_reference_does() {
    let dir = tempfile::tempdir().unwrap();
    for arch in [
        "bcq-actor",
        "cdt",
        "target-cost-mlp",
        "caps",
        "diffusion",
        "latent-policy",
    ] {
        let policy = dir.path().join(arch);
        crate::make_policy(&policy, TASK, arch, 5);
        let ours = evaluate(&policy, &["--episodes", "3", "--cost-threshold", "20"]);
        let theirs = python_reference(&policy, "20");
        let (ours, theirs) = (
            ours["episodes"].as_array().unwrap(),
            theirs["episodes"].as_array().unwrap(),
        );
        assert_eq!(ours.len(), 3, "{arch}");
        assert_eq!(ours.len(), theirs.len(), "{arch}");
        // Costs and lengths are equal; reward returns agree to float32 rounding (BLAS and candle's gemm sum in
        // different orders, and the evaluator batches and pads the CDT's contexts where the reference does not).
        for (a, b) in ours.iter().zip(theirs) {
            assert_eq!(
                (&a["seed"], &a["length"], &a["cost_return"]),
                (&b["seed"], &b["length"], &b["cost_return"]),
                "{arch}"
            );
            let (ra, rb) = (
                a["reward_return"].as_f64().unwrap(),
                b["reward_return"].as_f64().unwrap(),
            );
            assert!((ra - rb).abs() <= 1e-4 * rb.abs().max(1.0), "{arch}: {ra} vs {rb}");
        }
    }

    // Without --cost-threshold a conditioned policy plays at each of the task's thresholds; the target changes
    // what it does.
    let report = evaluate(&dir.path().join("cdt"), &["--episodes", "3"]);
    let thresholds = report["thresholds"].as_array().unwrap();
    assert_eq!(thresholds.len(), 3);
    let rewards = |t: &serde_json::Value| {
        t["episodes"]
            .as_array()
            .unwrap()
            .iter()
            .map(|e| e["reward_return"].as_f64().unwrap())
            .collect::<Vec<_>>()
    };
    assert_ne!(rewards(&thresholds[0]), rewards(&thresholds[2]));
    assert_eq!(thresholds[1]["cost_threshold"], 20.0);
}

/// The leaderboard's layout: fewer environments than episodes, so each environment plays several, in two
/// pipelined groups whose resets interleave with the other group's steps. Every seed is played once, in seed
/// order, and a second run gives the same episodes (answers are handled in the order requests were sent, not as
/// they happen to arrive). The CDT keeps a context per environment slot, so a slot mix-up would show.
#[test]
fn pipelined_groups_play_every_seed_once_and_deterministically() {
    let dir = tempfile::tempdir().unwrap();
    let policy = crate::make_policy(&dir.path().join("cdt"), TASK, "cdt", 7);
    let layout = [
        "--episodes",
        "7",
        "--sessions",
        "1",
        "--envs-per-session",
        "3",
        "--cost-threshold",
        "20",
    ];
    let episodes = |report: serde_json::Value| report["episodes"].as_array().unwrap().clone();
    let first = episodes(evaluate(&policy, &layout));
    let seeds: Vec<u64> = first.iter().map(|e| e["seed"].as_u64().unwrap()).collect();
    assert_eq!(seeds, (1_000_000..1_000_007).collect::<Vec<u64>>());
    assert!(first.iter().all(|e| e["length"].as_u64().unwrap() > 0));
    assert_eq!(first, episodes(evaluate(&policy, &layout)));
}
