//! The offline baselines end to end: `dsrl-train bcql|bearl|cpq|coptidice` train a few steps each on the committed
//! BallRun starter (real checkpoints, not good ones: the scores are not the point) and write one model per benchmark
//! threshold with the training recorded; `dsrl-train cdt` trains one model (at a small batch: OSRL's 2048 takes tens
//! of seconds a step) with OSRL's return targets; `dsrl-train caps` one model that takes each threshold as its
//! episode's cost budget; `dsrl-train fisor` and `dsrl-train lspc` one model each that takes several network passes
//! per action. `dsrl-admin reference` trains all ten, has the leaderboard score each on real
//! simulator workers with the paper's protocol (3 thresholds × 20 episodes), records each in the results file and
//! resumes without redoing anything.

use std::path::Path;
use std::process::Command;

use crate::leaderboard::{TASK, create_user, starter};

/// Trains `algorithm` for `steps` steps (per threshold, except CDT) into `out/<algorithm>`.
fn train(algorithm: &str, out: &Path, steps: u64, extra: &[&str]) -> String {
    let output = Command::new(dsrl_e2e::bin("dsrl-train"))
        .args([algorithm, "--task", TASK, "--steps", &steps.to_string(), "--seed", "1"])
        .args(extra)
        .arg("--dataset")
        .arg(starter())
        .arg("--out")
        .arg(out)
        .env_remove("DSRL_SERVER")
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "dsrl-train {algorithm} failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

/// Trains a per-threshold algorithm and checks its one line per threshold.
fn train_per_threshold(algorithm: &str, out: &Path, steps: u64) {
    let stdout = train(algorithm, out, steps, &[]);
    for k in [10, 20, 40] {
        assert!(
            stdout.contains(&format!("{algorithm}/threshold-{k}: {steps} steps")),
            "{stdout}"
        );
    }
}

#[test]
fn each_baseline_records_its_training_and_the_same_seed_trains_the_same_weights() {
    let models = tempfile::tempdir().unwrap();
    let algorithms = [
        ("bcql", "bcq_actor"),
        ("bearl", "squashed_gaussian_mlp"),
        ("cpq", "squashed_gaussian_mlp"),
        ("coptidice", "squashed_gaussian_mlp"),
    ];
    for (algorithm, _) in algorithms {
        train_per_threshold(algorithm, models.path(), 3);
        // The record names the algorithm, the budget, the seed and the per-step cost threshold it trained for.
        let config: serde_json::Value = serde_json::from_slice(
            &std::fs::read(models.path().join(algorithm).join("threshold-20/policy.json")).unwrap(),
        )
        .unwrap();
        let training = &config["training"];
        assert_eq!(training["algorithm"], algorithm, "{config}");
        assert_eq!(training["steps"], 3);
        assert_eq!(training["seed"], 1);
        assert_eq!(training["device"], "cpu", "{config}");
        assert!(training["qc_threshold"].as_f64().unwrap() > 0.0);
        assert!(
            training["settings"].as_str().unwrap().contains("batch_size: 512"),
            "{training}"
        );
        assert_eq!(config["conditioning"]["cost_threshold"], 20.0);
    }
    // A local file wins over DSRL_SERVER (which the README tells users to set), and its version id is recorded as a
    // fetched one would be: the id the file ingests to.
    let local = tempfile::tempdir().unwrap();
    let output = Command::new(dsrl_e2e::bin("dsrl-train"))
        .args(["bc", "--task", TASK, "--mode", "all", "--steps", "2", "--dataset"])
        .arg(starter())
        .arg("--out")
        .arg(local.path())
        .env("DSRL_SERVER", "http://127.0.0.1:9")
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(local.path().join("bc-all/policy.json")).unwrap()).unwrap();
    let catalog = dsrl_suite::Catalog::embedded().unwrap();
    let canonical = local.path().join("canonical.parquet");
    let (_, converted) = dsrl_suite::convert::import_file(
        &starter(),
        catalog.get(TASK).unwrap(),
        dsrl_suite::ObservationSpace::Simulator,
        &canonical,
    )
    .unwrap();
    assert_eq!(
        config["training"]["dataset_version"],
        converted.version.as_str(),
        "{config}"
    );
    assert!(
        config["training"]["code_commit"]
            .as_str()
            .is_some_and(|c| c.len() >= 12),
        "{config}"
    );

    // The same seed trains the same weights.
    let again = tempfile::tempdir().unwrap();
    train_per_threshold("cpq", again.path(), 3);
    let weights = |root: &Path| std::fs::read(root.join("cpq/threshold-10/policy.safetensors")).unwrap();
    assert_eq!(weights(models.path()), weights(again.path()));

    // CDT: one model, scored at each threshold from OSRL's BallRun targets (500; 10), (500; 20), (700; 40).
    let stdout = train("cdt", models.path(), 2, &["--batch-size", "64"]);
    assert!(stdout.contains("cdt: 2 steps"), "{stdout}");
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(models.path().join("cdt/policy.json")).unwrap()).unwrap();
    assert_eq!(config["architecture"]["name"], "cdt", "{config}");
    assert_eq!(config["conditioning"]["targets"][2]["reward_return"], 700.0, "{config}");
    assert!(
        config["training"]["settings"]
            .as_str()
            .unwrap()
            .contains("batch_size: 64")
    );
    assert!(
        config["training"]["departures"]
            .as_str()
            .unwrap()
            .contains("augmentation")
    );

    // CAPS: one model for every budget, the critics it switches with inside the checkpoint.
    let stdout = train("caps", models.path(), 3, &[]);
    assert!(stdout.contains("caps: 3 steps"), "{stdout}");
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(models.path().join("caps/policy.json")).unwrap()).unwrap();
    assert_eq!(config["architecture"]["name"], "caps", "{config}");
    assert_eq!(config["architecture"]["num_heads"], 5, "{config}");
    assert_eq!(
        config["architecture"]["episode_len"], 100,
        "BallRun's horizon: {config}"
    );
    assert_eq!(config["conditioning"]["kind"], "cost_budget", "{config}");
    assert_eq!(config["training"]["algorithm"], "caps", "{config}");
    assert_eq!(config["training"]["device"], "cpu", "{config}");

    // FISOR and LSPC: one model each for every threshold, their samplers and latents declared in the checkpoint.
    let stdout = train("fisor", models.path(), 2, &["--batch-size", "32"]);
    assert!(stdout.contains("fisor: 2 steps"), "{stdout}");
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(models.path().join("fisor/policy.json")).unwrap()).unwrap();
    let architecture = &config["architecture"];
    assert_eq!(architecture["name"], "diffusion", "{config}");
    assert_eq!(architecture["sampler"]["steps"], 5, "{config}");
    assert_eq!(architecture["sampler"]["candidates"], 16, "{config}");
    assert_eq!(architecture["sampler"]["choice"], "min_cost_q", "{config}");
    assert_eq!(config["conditioning"]["kind"], "unconditioned", "{config}");
    // A step draws the batch: the actor trains on its two halves, the critics on an eighth.
    let settings = config["training"]["settings"].as_str().unwrap();
    assert!(
        settings.contains("actor_batch: 16") && settings.contains("critic_batch: 4"),
        "{settings}"
    );
    assert_eq!(config["training"]["batch_size"], 32, "{config}");
    let stdout = train("lspc", models.path(), 2, &["--batch-size", "32"]);
    assert!(stdout.contains("lspc: 2 steps"), "{stdout}");
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(models.path().join("lspc/policy.json")).unwrap()).unwrap();
    assert_eq!(config["architecture"]["name"], "latent_policy", "{config}");
    assert_eq!(config["architecture"]["latent"], "safety_encoder", "{config}");
    // BallRun is one of the Bullet tasks LSPC bounds its latent at 0.6 on.
    assert_eq!(config["architecture"]["max_latent"], 0.6, "{config}");
    for method in ["FISOR", "LSPC"] {
        let output = Command::new(dsrl_e2e::bin("dsrl-train"))
            .args([
                &method.to_lowercase(),
                "--task",
                TASK,
                "--steps",
                "1",
                "--cost-threshold",
                "10",
            ])
            .arg("--dataset")
            .arg(starter())
            .env_remove("DSRL_SERVER")
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(
            !output.status.success() && stderr.contains(&format!("{method} is trained once")),
            "{stderr}"
        );
    }

    // Every method takes --device; this build (CI's, without the `cuda` feature) says how to get a GPU build
    // instead of training anywhere else.
    for algorithm in [
        "bc",
        "bcql",
        "bearl",
        "cpq",
        "coptidice",
        "cdt",
        "caps",
        "fisor",
        "lspc",
    ] {
        let mode: &[&str] = if algorithm == "bc" { &["--mode", "all"] } else { &[] };
        let output = Command::new(dsrl_e2e::bin("dsrl-train"))
            .args([algorithm, "--task", TASK, "--steps", "1", "--device", "cuda"])
            .args(mode)
            .arg("--dataset")
            .arg(starter())
            .arg("--out")
            .arg(models.path().join("cuda"))
            .env_remove("DSRL_SERVER")
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{algorithm}: {stderr}");
        assert!(stderr.contains("without the `cuda` feature"), "{algorithm}: {stderr}");
    }
    assert!(
        !models.path().join("cuda").exists(),
        "nothing is written for a device that is not there"
    );

    // Each of these is scored by the leaderboard in the reference command's test below (every method, trained by
    // the command and scored with the paper's protocol), which makes its own checkpoints the same way.
}

/// `dsrl-admin reference`, the one command that reproduces the reference table from its plan, end to end on a
/// server hosting the BallRun starter: it trains every method (a few steps, two jobs at a time: one per threshold
/// for the per-threshold methods), submits each entry in turn and waits for its score.
#[test]
fn the_reference_command_trains_scores_and_records_every_method_and_resumes() {
    // Two episodes per threshold: the command's path, not the protocol's count, is what is tested (the protocol's
    // twenty are scored in the leaderboard's own test).
    let (env, token) = scoring_server(&[
        ("DSRL__SIMULATORS__LOCAL_WORKERS", "2"),
        ("DSRL__LEADERBOARD__EPISODES_PER_THRESHOLD", "2"),
        ("DSRL__LEADERBOARD__ENVS_PER_SESSION", "2"),
    ]);
    let state = env.path("reference-state");
    let results = env.path("results.jsonl");
    let plan = concat!(
        "methods = [\"bc-all\", \"bc-safe\", \"cdt\", \"bcql\", \"bearl\", \"cpq\", \"coptidice\", ",
        "\"caps\", \"fisor\", \"lspc\"]\n",
        "steps = 3\nsteps_for = { cdt = 1, caps = 3 }\nbatch_size = 16\n"
    );
    let run = |extra: &[&str]| reference(&env, &token, plan, &[&["--jobs", "2"], extra].concat());
    let output = run(&[]);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "dsrl-admin reference failed: {stderr}");
    assert!(stderr.contains("training 20 models (2 at a time)"), "{stderr}");
    // BEAR-Lag trains three times --steps, as OSRL's 300,000 against 100,000.
    let policies = state.join("policies").join(TASK).join("seed-0");
    let bearl: serde_json::Value =
        serde_json::from_slice(&std::fs::read(policies.join("bearl/threshold-40/policy.json")).unwrap()).unwrap();
    assert_eq!(bearl["training"]["steps"], 9, "{bearl}");

    // Every entry was scored and recorded, under the server's protocol, with its budget and episodes.
    let board = crate::get_json(&format!("{}/v1/leaderboard?task={TASK}", env.server.url));
    let protocol = board["protocol"]["version"].as_str().unwrap().to_owned();
    let catalog = dsrl_suite::Catalog::embedded().unwrap();
    let text = std::fs::read_to_string(&results).unwrap();
    let entries = dsrl_scoring::reference::read_results(&text, &catalog).unwrap();
    let mut methods: Vec<&str> = entries.iter().map(|e| e.method.as_str()).collect();
    methods.sort_unstable();
    assert_eq!(
        methods,
        [
            "BC-All",
            "BC-Safe",
            "BCQ-Lag",
            "BEAR-Lag",
            "CAPS",
            "CDT",
            "COptiDICE",
            "CPQ",
            "FISOR",
            "LSPC"
        ]
    );
    let shown = board["tasks"][0]["entries"].as_array().unwrap();
    for e in &entries {
        assert_eq!(e.protocol_version, protocol);
        assert_eq!(e.episodes.len(), 6, "{}", e.method);
        assert_eq!(
            e.training.models,
            if ["BC-All", "CDT", "CAPS", "FISOR", "LSPC"].contains(&e.method.as_str()) {
                1
            } else {
                3
            }
        );
        assert!(
            e.training.cpu_seconds > 0.0 && !e.code_commit.is_empty(),
            "{}",
            e.method
        );
        // The CPU its seconds were measured on (Linux: /proc/cpuinfo names it).
        let cpu = e.training.cpu.as_deref().unwrap_or_default();
        assert!(cpu.contains("AVX-512: "), "{}: {cpu:?}", e.method);
        // The line's scores are the server's.
        let row = shown.iter().find(|r| r["submission"] == e.scoring.submission).unwrap();
        let score = e.score(catalog.get(TASK).unwrap()).unwrap();
        assert_eq!(row["normalized_reward"].as_f64().unwrap(), score.reward);
        assert_eq!(row["normalized_cost"].as_f64().unwrap(), score.cost);
        assert_eq!(row["safe"], score.is_safe());
        assert_eq!(row["dataset_version"], e.dataset_version.as_str());
    }

    // A second run finds everything done: it trains, submits and changes nothing. It goes by the results file, not
    // by its state folder: so does a fresh machine's run over the committed results.
    std::fs::remove_dir_all(state.join("policies")).unwrap();
    let again = run(&[]);
    let stderr = String::from_utf8_lossy(&again.stderr);
    assert!(again.status.success(), "{stderr}");
    assert!(!stderr.contains("submitted as"), "{stderr}");
    assert!(!stderr.contains("training "), "{stderr}");
    assert_eq!(stderr.matches("not trained again").count(), 10, "{stderr}");
    assert_eq!(std::fs::read_to_string(&results).unwrap(), text);
    let board = crate::get_json(&format!("{}/v1/leaderboard?task={TASK}", env.server.url));
    assert_eq!(board["tasks"][0]["entries"].as_array().unwrap().len(), 10);

    // Trained again from scratch (--reproduce), every method's checkpoints come out with the digest their entry was
    // scored with: training is deterministic given its seed, and the entry keeps its scoring. A dsrl-train built
    // from uncommitted sources (a working tree, not CI's clone) may not put its name on an entry: then each
    // reproduction is refused for that reason, after its networks were checked, and the file is left alone.
    let reproduced = run(&["--reproduce"]);
    let stderr = String::from_utf8_lossy(&reproduced.stderr);
    assert!(!stderr.contains("submitted as"), "{stderr}");
    let reproduced_bearl = state.join("reproduced/policies").join(TASK).join("seed-0/bearl");
    assert!(reproduced_bearl.join("threshold-40").is_dir());
    let after = dsrl_scoring::reference::read_results(&std::fs::read_to_string(&results).unwrap(), &catalog).unwrap();
    if entries[0].code_commit.ends_with("-modified") {
        // Refused for its uncommitted build only after the networks were found to be the scored ones.
        assert!(!reproduced.status.success(), "{stderr}");
        assert_eq!(stderr.matches("reproduced the scored networks").count(), 10, "{stderr}");
        assert_eq!(std::fs::read_to_string(&results).unwrap(), text);
    } else {
        assert!(
            reproduced.status.success(),
            "not every method trained to the same networks: {stderr}"
        );
        assert!(stderr.contains("every entry reproduced"), "{stderr}");
        assert_eq!(after.len(), entries.len());
        for (old, new) in entries.iter().zip(&after) {
            assert_eq!(
                (&new.method, &new.checkpoint_sha256),
                (&old.method, &old.checkpoint_sha256)
            );
            assert_eq!((&new.episodes, &new.scoring), (&old.episodes, &old.scoring));
            assert_eq!(new.code_commit, old.code_commit);
        }
    }
}

/// A scoring the leaderboard fails as the checkpoint's fault (here: a policy memory limit too small to load any
/// weights) would fail again, and the server refuses the same checkpoint while that submission stands: the command
/// stops with the reason after one submission instead of "retrying" the submission it already has.
#[test]
fn the_reference_command_stops_at_a_scoring_failed_for_the_checkpoints_sake() {
    let (env, token) = scoring_server(&[
        ("DSRL__SIMULATORS__LOCAL_WORKERS", "1"),
        ("DSRL__LEADERBOARD__POLICY_MEMORY_LIMIT_BYTES", "50000000"),
        // The limit holds in the policy process: the BC network would otherwise act in the workers.
        ("DSRL__LEADERBOARD__ACT_IN_WORKERS_MAX_MULTIPLY_ADDS", "0"),
    ]);
    let output = reference(
        &env,
        &token,
        "methods = [\"bc-all\"]\nsteps = 3\nbatch_size = 16\n",
        &[],
    );
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "{stderr}");
    assert!(stderr.contains("MB memory limit"), "{stderr}");
    assert!(
        stderr.contains("as the checkpoint's fault: not submitted again"),
        "{stderr}"
    );
    assert_eq!(stderr.matches("submitted as").count(), 1, "{stderr}");
    assert!(!env.path("results.jsonl").exists(), "nothing is recorded");
}

/// A model whose training fails leaves no marker (a rerun trains it again rather than taking it for done) and
/// stops the command once the models training beside it have finished (their work is kept); a command stopped by a
/// signal stops its models too, so none trains on beside the copies a rerun would start.
#[test]
fn the_reference_command_stops_whole_at_a_failed_training_or_a_signal() {
    let (env, token) = scoring_server(&[("DSRL__SIMULATORS__LOCAL_WORKERS", "1")]);
    let models = env.path("reference-state").join("policies").join(TASK).join("seed-0");
    let markers = || -> Vec<String> {
        let mut found: Vec<String> = std::fs::read_dir(&models)
            .map(|d| {
                d.map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                    .collect()
            })
            .unwrap_or_default();
        found.retain(|n| n.starts_with(".trained"));
        found
    };
    // BCQ-Lag cannot write its models: a file stands where its folder goes.
    std::fs::create_dir_all(&models).unwrap();
    std::fs::write(models.join("bcql"), b"in the way").unwrap();
    let output = reference(
        &env,
        &token,
        "methods = [\"bc-all\", \"bcql\"]\nsteps = 3\n",
        &["--jobs", "2"],
    );
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "{stderr}");
    assert!(stderr.contains("failed to train"), "{stderr}");
    assert_eq!(markers(), [".trained-bc-all---steps-3-batch-osrl"], "{stderr}");

    // Stopped while BC-All trains (long enough to be still training): nothing is left training into the state.
    let state = env.path("reference-state").display().to_string();
    let training = || -> usize {
        std::fs::read_dir("/proc")
            .unwrap()
            .filter_map(|e| std::fs::read(e.ok()?.path().join("cmdline")).ok())
            .map(|c| String::from_utf8_lossy(&c).replace('\0', " "))
            .filter(|c| c.contains(&state) && c.contains("dsrl-train bc"))
            .count()
    };
    let mut command = reference_command(&env, &token, "methods = [\"bc-all\"]\nsteps = 100000000\n", &[])
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    while training() == 0 {
        assert!(std::time::Instant::now() < deadline, "BC-All never started training");
        std::thread::sleep(std::time::Duration::from_millis(200));
    }
    let kill = Command::new("kill").args(["-TERM", &command.id().to_string()]).status();
    assert!(kill.unwrap().success());
    assert!(!command.wait().unwrap().success());
    std::thread::sleep(std::time::Duration::from_millis(500));
    assert_eq!(training(), 0, "a model trains on after its command stopped");
    assert_eq!(markers(), [".trained-bc-all---steps-3-batch-osrl"]);
}

/// All of a run's tasks train in one pool (a task's last models beside the next task's first, no core waiting for a
/// task to finish), and each method is handed in as soon as its own models have trained, whichever task it is of.
#[test]
fn the_reference_command_trains_all_its_tasks_in_one_pool() {
    const CAR_RUN: &str = "OfflineCarRun-v0";
    let (env, token) = scoring_server(&[
        ("DSRL__SIMULATORS__LOCAL_WORKERS", "2"),
        ("DSRL__LEADERBOARD__EPISODES_PER_THRESHOLD", "2"),
        ("DSRL__LEADERBOARD__ENVS_PER_SESSION", "2"),
    ]);
    let car_run = dsrl_e2e::repo_root().join("data/starter/OfflineCarRun-v0/SafetyCarRun-v0-40-590.parquet");
    env.cli
        .run(&["admin", "ingest", "--task", CAR_RUN, crate::s(&car_run)])
        .ok();
    let plan = format!("tasks = [\"{CAR_RUN}\", \"{TASK}\"]\nmethods = [\"bc-all\"]\nsteps = 3\nbatch_size = 16\n");
    let output = reference(&env, &token, &plan, &["--jobs", "2"]);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    assert_eq!(stderr.matches("training ").count(), 1, "{stderr}");
    assert!(
        stderr.contains(&format!("training 2 models (2 at a time) of {CAR_RUN} {TASK}")),
        "{stderr}"
    );
    let catalog = dsrl_suite::Catalog::embedded().unwrap();
    let text = std::fs::read_to_string(env.path("results.jsonl")).unwrap();
    let mut recorded: Vec<(String, String)> = dsrl_scoring::reference::read_results(&text, &catalog)
        .unwrap()
        .into_iter()
        .map(|e| (e.task, e.method))
        .collect();
    recorded.sort();
    assert_eq!(
        recorded,
        [(TASK, "BC-All"), (CAR_RUN, "BC-All")].map(|(t, m)| (t.to_owned(), m.to_owned()))
    );
}

/// A server hosting the BallRun starter on its own simulator workers, with `settings`, and a user's token.
fn scoring_server(settings: &[(&str, &str)]) -> (crate::Env, String) {
    let binary = dsrl_e2e::bin("dsrl-sim-worker").display().to_string();
    let env = crate::Env::with(
        &[],
        &[&[("DSRL__SIMULATORS__WORKER_BINARY", binary.as_str())], settings].concat(),
    );
    env.cli
        .run(&["admin", "ingest", "--task", TASK, crate::s(&starter())])
        .ok();
    let token = create_user(&env, "reference");
    (env, token)
}

/// `dsrl-admin reference` over a plan of one phase with one run (`run`: the keys of a `[[phase.run]]`, on BallRun
/// unless it names `tasks`) against `env`'s server as the user of `token`, its state and results file in `env`'s
/// folder.
fn reference(env: &crate::Env, token: &str, run: &str, args: &[&str]) -> std::process::Output {
    reference_command(env, token, run, args).output().unwrap()
}

fn reference_command(env: &crate::Env, token: &str, run: &str, args: &[&str]) -> Command {
    let plan = env.path("plan.toml");
    let tasks = if run.contains("tasks =") {
        String::new()
    } else {
        format!("tasks = [\"{TASK}\"]\n")
    };
    std::fs::write(
        &plan,
        format!("[[phase]]\nname = \"test\"\nabout = \"the e2e test's\"\n[[phase.run]]\n{tasks}{run}"),
    )
    .unwrap();
    let mut command = Command::new(dsrl_e2e::bin("dsrl-admin"));
    command
        .current_dir(dsrl_e2e::repo_root())
        .args(["reference", "test", "--plan"])
        .arg(&plan)
        .args(args)
        .arg("--state")
        .arg(env.path("reference-state"))
        .arg("--results")
        .arg(env.path("results.jsonl"))
        .args(["--server", &env.server.url, "--token", token, "--user", "reference"])
        .env("DSRL_TRAIN", dsrl_e2e::bin("dsrl-train"))
        .env("DSRL_DATASET_DIR", env.path("cache"));
    command
}
