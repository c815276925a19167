//! Expert recipes end to end through `dsrl-admin collect` on real simulator workers: a short PPO-Lagrangian run on
//! a Bullet task, killed after a save and resumed, gives the same dataset as an uninterrupted run, is ingested
//! with its provenance and leaves a loadable expert policy; every Safety-Gymnasium recipe runs with a tiny budget.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use crate::Env;

/// A task's committed recipe with fewer environments per collect and saves every `every` collects.
fn small_recipe(dir: &Path, task: &str, envs: u32, every: u32) -> PathBuf {
    let text = std::fs::read_to_string(dsrl_e2e::repo_root().join(format!("data/recipes/{task}.toml"))).unwrap();
    // The save interval differs between recipes (25 collects; 5 for the 1000-step Safety-Gymnasium episodes).
    let small: String = text
        .replace("envs = 10 ", &format!("envs = {envs} "))
        .lines()
        .map(|line| {
            if line.starts_with("checkpoint_every_collects = ") {
                format!("checkpoint_every_collects = {every}\n")
            } else {
                format!("{line}\n")
            }
        })
        .collect();
    assert!(
        small.contains(&format!("envs = {envs} ")) && small.contains(&format!("checkpoint_every_collects = {every}")),
        "{task}: the recipe's layout changed"
    );
    let path = dir.join(format!("{task}.toml"));
    std::fs::write(&path, small).unwrap();
    path
}

fn collect(task: &str, recipe: &Path, state: &Path, budget: u64, workers: u32, extra: &[&str]) -> Command {
    let (workers, budget) = (workers.to_string(), budget.to_string());
    let flags = [
        &["--workers", workers.as_str(), "--budget-steps", budget.as_str()],
        extra,
    ]
    .concat();
    crate::admin_collect(task, recipe, state, &flags)
}

#[test]
fn a_killed_bullet_expert_run_resumes_to_the_same_dataset_and_ingests_with_provenance() {
    const TASK: &str = "OfflineBallRun-v0";
    let env = Env::new();
    // 4 environments of 100-step episodes: 400 steps per collect, a save every 2 collects, 12 collects.
    let recipe = small_recipe(env.dir.path(), TASK, 4, 2);
    let budget = 4800;

    let reference = crate::admin_json(collect(TASK, &recipe, &env.path("reference"), budget, 1, &[]));
    let version = reference["version"].as_str().unwrap().to_owned();
    let details = &reference["provenance"]["details"];
    assert_eq!(details["collects"], 12);
    assert_eq!(
        details["steps_trained"], 4800,
        "BallRun episodes run to the 100-step limit"
    );
    assert_eq!(details["episodes_collected"], 48);
    assert!(reference["episodes"].as_u64().unwrap() >= 1);

    // Killed once the first save exists, then resumed with two workers (the 4 environments now in two sessions of
    // 2, not one of 4: the grouping must not change the data) and ingested.
    let state = env.path("killed");
    crate::kill_once_saved(
        collect(TASK, &recipe, &state, budget, 1, &[]),
        &state.join("expert/ckpt-000002/state.json"),
        &state.join("expert/ckpt-000012"),
    );
    let token = env.server.token();
    let resumed = crate::admin_json(collect(
        TASK,
        &recipe,
        &state,
        budget,
        2,
        &["--server", &env.server.url, "--token", &token, "--tag", "expert-tiny"],
    ));
    assert_eq!(resumed["version"], version.as_str(), "resuming changed the dataset");
    assert_eq!(resumed["ingested"]["created"], true);

    let manifest = crate::get_json(&format!("{}/v1/datasets/{TASK}/versions/expert-tiny", env.server.url));
    assert_eq!(manifest["version"], version.as_str());
    let provenance = &manifest["provenance"];
    assert_eq!(provenance["kind"], "recipe");
    assert_eq!(provenance["details"]["budget_steps"], 4800);
    assert_eq!(provenance["details"]["paper_steps"], 10_000_000);
    assert_eq!(provenance["details"]["recipe"]["expert"]["algorithm"], "ppo_lagrangian");

    // The training log covers every collect once, and the expert is saved in the evaluator's policy format.
    let log = std::fs::read_to_string(state.join("expert/training.csv")).unwrap();
    assert_eq!(log.lines().count(), 1 + 12);
    let policy: serde_json::Value =
        serde_json::from_slice(&std::fs::read(state.join("expert/policy/policy.json")).unwrap()).unwrap();
    assert_eq!(policy["task"], TASK);
    assert_eq!(
        (policy["obs_dim"].as_u64(), policy["act_dim"].as_u64()),
        (Some(7), Some(2))
    );
    assert_eq!(policy["architecture"]["name"], "gaussian_mlp");
    assert!(state.join("expert/policy/policy.safetensors").is_file());

    // The expert can be scored like any policy: `dsrl-admin evaluate` plays it on the real simulator.
    let evaluate = |dir: &Path| {
        Command::new(dsrl_e2e::bin("dsrl-admin"))
            .args(["evaluate", "--episodes", "3", "--workers", "1", "--json"])
            .arg(dir)
            .output()
            .unwrap()
    };
    let out = evaluate(&state.join("expert/policy"));
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let episodes = report["episodes"].as_array().unwrap();
    assert_eq!(episodes.len(), 3);
    assert!(episodes.iter().all(|e| e["length"] == 100));
    let mean = episodes
        .iter()
        .map(|e| e["reward_return"].as_f64().unwrap())
        .sum::<f64>()
        / 3.0;
    assert!((report["mean_reward_return"].as_f64().unwrap() - mean).abs() < 1e-9);
    assert_eq!(report["thresholds"].as_array().unwrap().len(), 3);
    // Deterministic actions and fixed seeds: the same score again.
    let again: serde_json::Value = serde_json::from_slice(&evaluate(&state.join("expert/policy")).stdout).unwrap();
    assert_eq!(again["episodes"], report["episodes"]);

    // A BC-Safe reference policy trained on the ingested version (fetched from the server into a dataset cache)
    // is written in the same format and scored at its own threshold only.
    let out = Command::new(dsrl_e2e::bin("dsrl-train"))
        .args([
            "bc",
            "--task",
            TASK,
            "--mode",
            "safe",
            "--cost-threshold",
            "40",
            "--steps",
            "50",
        ])
        .args(["--server", &env.server.url, "--version", "expert-tiny"])
        .arg("--out")
        .arg(env.path("bc"))
        .env("DSRL_DATASET_DIR", env.path("cache"))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let bc_policy: serde_json::Value =
        serde_json::from_slice(&std::fs::read(env.path("bc/bc-safe/threshold-40/policy.json")).unwrap()).unwrap();
    assert_eq!(bc_policy["architecture"]["name"], "mlp_actor");
    assert_eq!(bc_policy["conditioning"]["cost_threshold"], 40.0);
    assert_eq!(bc_policy["training"]["dataset_version"], version.as_str());
    let out = evaluate(&env.path("bc/bc-safe/threshold-40"));
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["thresholds"].as_array().unwrap().len(), 1);
    assert_eq!(report["thresholds"][0]["cost_threshold"], 40.0);

    // Parity: the same checkpoints played in-process in Python (NumPy forward pass, the simulator objects directly)
    // give the same episodes. Costs and lengths are equal; reward returns agree to float32 rounding, because BLAS
    // and candle's gemm sum the matrix products in different orders.
    for (dir, report) in [
        (state.join("expert/policy"), &again),
        (env.path("bc/bc-safe/threshold-40"), &report),
    ] {
        let out = Command::new(dsrl_e2e::repo_root().join(".venv-sim/bin/python"))
            .arg(dsrl_e2e::repo_root().join("tests/parity/evaluate_in_python.py"))
            .arg(&dir)
            .args(["--sim-id", "SafetyBallRun-v0", "--episodes", "3"])
            .stderr(Stdio::inherit())
            .output()
            .unwrap();
        assert!(out.status.success(), "the Python reference failed");
        let python: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        let (ours, theirs) = (
            report["episodes"].as_array().unwrap(),
            python["episodes"].as_array().unwrap(),
        );
        assert_eq!(ours.len(), theirs.len());
        for (a, b) in ours.iter().zip(theirs) {
            assert_eq!(
                (&a["seed"], &a["length"], &a["cost_return"]),
                (&b["seed"], &b["length"], &b["cost_return"])
            );
            let (ra, rb) = (
                a["reward_return"].as_f64().unwrap(),
                b["reward_return"].as_f64().unwrap(),
            );
            assert!(
                (ra - rb).abs() <= 1e-5 * rb.abs().max(1.0),
                "{}: {ra} vs {rb}",
                dir.display()
            );
        }
    }

    // A checkpoint whose declared dimensions disagree with the task is refused with the reason.
    let broken = env.path("broken-policy");
    std::fs::create_dir_all(&broken).unwrap();
    std::fs::copy(
        state.join("expert/policy/policy.safetensors"),
        broken.join("policy.safetensors"),
    )
    .unwrap();
    let mut config = policy.clone();
    config["obs_dim"] = serde_json::json!(8);
    std::fs::write(broken.join("policy.json"), config.to_string()).unwrap();
    let out = evaluate(&broken);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("observation dim 7") && stderr.contains("declares 8"),
        "{stderr}"
    );
}

#[test]
fn a_warm_started_expert_starts_from_its_source_build_and_records_it() {
    const SOURCE: &str = "OfflineBallRun-v0";
    // CarRun has BallRun's observation and action dimensions (7, 2), so a BallRun expert can start it.
    const TASK: &str = "OfflineCarRun-v0";
    let env = Env::new();
    let collect_dir = env.path("collect");
    // The source: BallRun, 2 environments of 100-step episodes, 4 collects, a save every 2.
    let source = collect_dir.join(SOURCE);
    crate::admin_json(collect(
        SOURCE,
        &small_recipe(env.dir.path(), SOURCE, 2, 2),
        &source,
        800,
        1,
        &[],
    ));
    let source_weights = source.join("expert/ckpt-000004/state.safetensors");
    assert!(source_weights.is_file());

    let fresh_recipe = small_recipe(env.dir.path(), TASK, 2, 2);
    let warm_recipe = |budget: u64| {
        let path = env.path(&format!("warm-{budget}.toml"));
        let text = std::fs::read_to_string(&fresh_recipe).unwrap()
            + &format!("\n[expert.warm_start]\ntask = \"{SOURCE}\"\nbudget_steps = {budget}\n");
        std::fs::write(&path, text).unwrap();
        path
    };
    let refused = |recipe: &Path, state: &Path| {
        let out = collect(TASK, recipe, state, 800, 1, &[]).output().unwrap();
        assert!(!out.status.success());
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    // No source beside the state folder: refused with the command that builds it, before anything is simulated.
    let err = refused(&warm_recipe(800), &env.path("elsewhere").join(TASK));
    assert!(
        err.contains("BUDGET_STEPS=800 data/build_datasets.sh OfflineBallRun-v0") && err.contains("--warm-start"),
        "{err}"
    );
    assert!(!env.path("elsewhere").join(TASK).join("expert/ckpt-000002").exists());
    // A source of another budget than the recipe names: refused.
    let err = refused(&warm_recipe(1600), &collect_dir.join(TASK));
    assert!(err.contains("holds a build of OfflineBallRun-v0 at 800 steps"), "{err}");

    // Beside its source, and from a folder named with --warm-start: the same run, recorded in the provenance.
    std::fs::remove_dir_all(collect_dir.join(TASK)).unwrap();
    let warm = crate::admin_json(collect(TASK, &warm_recipe(800), &collect_dir.join(TASK), 800, 1, &[]));
    let record = &warm["provenance"]["details"]["warm_start"];
    assert_eq!(record["task"], SOURCE);
    assert_eq!(record["steps_trained"], 800);
    assert_eq!(record["recipe"]["task"], SOURCE);
    assert_eq!(record["state_sha256"], crate::sha256_file(&source_weights).as_str());
    let named = crate::admin_json(collect(
        TASK,
        &warm_recipe(800),
        &env.path("named"),
        800,
        1,
        &["--warm-start", crate::s(&source)],
    ));
    assert_eq!(named["version"], warm["version"]);

    // A fresh expert plays its first collect with other weights: other returns, another dataset.
    let fresh = crate::admin_json(collect(TASK, &fresh_recipe, &env.path("fresh"), 800, 1, &[]));
    assert!(fresh["provenance"]["details"].get("warm_start").is_none());
    assert_ne!(fresh["version"], warm["version"]);
    let first_collect = |state: &Path| {
        let log = std::fs::read_to_string(state.join("expert/training.csv")).unwrap();
        log.lines().nth(1).unwrap().split(',').nth(3).unwrap().to_owned()
    };
    assert_ne!(
        first_collect(&collect_dir.join(TASK)),
        first_collect(&env.path("fresh")),
        "the first collect's mean reward"
    );
}

/// Two Safety-Gymnasium recipes, a navigation task's and a velocity task's, each through one tiny collect; every one
/// of the 21 runs in the long check below.
#[test]
fn a_navigation_and_a_velocity_recipe_collect_a_dataset_with_a_tiny_budget() {
    recipes_collect(&[
        "OfflinePointGoal1Gymnasium-v0",
        "OfflineHalfCheetahVelocityGymnasium-v1",
    ]);
}

#[test]
#[ignore = "long check (scripts/long-checks.sh): all 21 recipes; CI runs one navigation and one velocity recipe"]
fn every_safety_gymnasium_recipe_collects_a_dataset_with_a_tiny_budget() {
    let recipes = dsrl_e2e::repo_root().join("data/recipes");
    let mut tasks: Vec<String> = std::fs::read_dir(&recipes)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|n| n.contains("Gymnasium"))
        .map(|n| n.trim_end_matches(".toml").to_owned())
        .collect();
    tasks.sort();
    assert_eq!(tasks.len(), 21);
    recipes_collect(&tasks.iter().map(String::as_str).collect::<Vec<_>>());
}

/// One collect of two episodes of each task's recipe, with every return admitted.
fn recipes_collect(tasks: &[&str]) {
    let env = Env::new();
    for &task in tasks {
        // One collect of two episodes (1000 steps or fewer each). An untrained policy's returns are often negative
        // or its costs above the cap, which the recipe's buffer and final grid rightly drop (the paper's datasets
        // hold neither), so this copy admits every return: the test is about the pipeline running on each task.
        let recipe = small_recipe(env.dir.path(), task, 2, 1);
        // A recipe that warm-starts from another task's build (PointPush2's) runs here from fresh weights: the warm
        // start needs that build, and has its own test above.
        let mut in_warm_start = false;
        let text: Vec<String> = std::fs::read_to_string(&recipe)
            .unwrap()
            .lines()
            .filter(|line| {
                if line.starts_with('[') {
                    in_warm_start = line.starts_with("[expert.warm_start]");
                }
                !in_warm_start
            })
            .map(|line| match line.split(" =").next().unwrap() {
                "reward_range" => "reward_range = [-5000.0, 9999.0]".to_owned(),
                "cost_range" => "cost_range = [0.0, 5000.0]".to_owned(),
                "cost_cap" => "cost_cap = 5000".to_owned(),
                _ => line.to_owned(),
            })
            .collect();
        assert_eq!(
            text.iter().filter(|l| l.contains("5000")).count(),
            4,
            "{task}: the recipe's layout changed"
        );
        std::fs::write(&recipe, text.join("\n")).unwrap();
        let mut cmd = collect(task, &recipe, &env.path(task), 1, 1, &[]);
        let out = cmd.output().unwrap();
        // The workers' logs fill stderr; on failure, show what is not routine.
        let stderr = String::from_utf8_lossy(&out.stderr);
        let unusual: Vec<&str> = stderr
            .lines()
            .filter(|l| !l.contains("INFO") && !l.contains("Adroit"))
            .collect();
        assert!(
            out.status.success(),
            "{task}: dsrl-admin failed:\n{}",
            unusual[unusual.len().saturating_sub(40)..].join("\n")
        );
        let out: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        let details = &out["provenance"]["details"];
        assert_eq!(details["collects"], 1, "{task}");
        assert_eq!(details["episodes_collected"], 2, "{task}");
        assert!(out["episodes"].as_u64().unwrap() >= 1, "{task}: {out}");
        assert!(Path::new(out["file"].as_str().unwrap()).is_file(), "{task}");
    }
}
