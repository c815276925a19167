//! `dsrl-admin build` end to end on real simulator workers, with a tiny plan (`fixtures/full_builds.toml`):
//! BallRun's build, killed after a save, resumes to the version id committed in `fixtures/full/` (so a change that
//! alters what builds produce fails here), and so does one on three workers rather than one; uploaded to a server that holds the committed starter, it becomes
//! `latest`, tagged `full`, with the starter still reachable under `starter` and each said to be what it is; a build
//! whose committed identity differs fails and names the first episode that differs.

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::{Env, s};

const TASK: &str = "OfflineBallRun-v0";

fn fixtures() -> PathBuf {
    dsrl_e2e::repo_root().join("tests/e2e/fixtures")
}

/// The committed identity of the tiny build. A build's bytes depend on the CPU's matrix kernels (data/README.md);
/// gemm is built without its AVX-512 ones, so AVX2 and AVX-512 machines run the same (AVX2, FMA) kernels and build
/// the same bytes: one identity holds on both (checked on each kind). A CPU without FMA would need one of its own.
fn committed_records() -> PathBuf {
    let kernels = dsrl_policy::matrix_kernels();
    assert_eq!(
        kernels, "AVX2",
        "the tiny build's committed identity (fixtures/full/) was made with AVX2 kernels; this CPU runs {kernels} ones"
    );
    fixtures().join("full")
}

/// `dsrl-admin build TASK` with the tiny plan on `workers` simulator workers, its records in `records` and its state
/// under `root`.
fn build(root: &Path, records: &Path, workers: u32, extra: &[&str]) -> Command {
    let mut cmd = Command::new(dsrl_e2e::bin("dsrl-admin"));
    cmd.current_dir(dsrl_e2e::repo_root())
        .args(["build", "--json", "--workers", &workers.to_string(), "--plan"])
        .arg(fixtures().join("full_builds.toml"))
        .arg("--records")
        .arg(records)
        .arg("--root")
        .arg(root)
        .args(extra)
        .arg(TASK)
        .env_remove("DSRL_SERVER")
        .env_remove("DSRL_ADMIN_TOKEN");
    cmd
}

#[test]
fn a_killed_full_build_resumes_to_its_committed_identity_uploads_as_latest_and_a_changed_one_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let starters = crate::dsrl_download::starters(dir.path(), &[TASK]);
    let env = Env::with(&["--starter-datasets", s(&starters)], &[]);
    let committed: serde_json::Value =
        serde_json::from_slice(&std::fs::read(committed_records().join(format!("{TASK}.json"))).unwrap()).unwrap();
    let version = committed["version"].as_str().unwrap().to_owned();

    // Killed once the first save exists (the build is a child of the command: it goes with it), then resumed.
    let root = dir.path().join("root");
    let state = root.join(TASK);
    crate::kill_once_saved(
        build(&root, &committed_records(), 1, &[]),
        &state.join("expert/ckpt-000002/state.json"),
        &state.join("record"),
    );
    let token = env.server.token();
    let outcomes = crate::admin_json(build(
        &root,
        &committed_records(),
        1,
        &["--server", &env.server.url, "--token", &token],
    ));
    let outcome = &outcomes[0];
    assert_eq!(outcome["check"], "matches", "{outcome:#}");
    assert_eq!(
        outcome["version"],
        version.as_str(),
        "the resumed build differs from the committed identity"
    );
    let compute: serde_json::Value =
        serde_json::from_slice(&std::fs::read(state.join("compute.json")).unwrap()).unwrap();
    assert_eq!(compute["runs"], 2, "the killed run and the resumed one: {compute}");
    assert!(compute["cpu_seconds"].as_f64().unwrap() > 0.0, "{compute}");

    // On the server: the build is latest and `full`; the starter keeps its tag and says what it is.
    let url = |reference: &str| format!("{}/v1/datasets/{TASK}/versions/{reference}", env.server.url);
    let latest = crate::get_json(&url("latest"));
    assert_eq!(latest["version"], version.as_str());
    assert_eq!(latest["hosting"]["kind"], "full");
    assert!(latest["hosting"]["notice"].is_null());
    assert_eq!(crate::get_json(&url("full"))["version"], version.as_str());
    let starter = crate::get_json(&url("starter"));
    assert_ne!(starter["version"], version.as_str());
    assert_eq!(starter["hosting"]["kind"], "starter");
    assert_eq!(starter["hosting"]["paper_trajectories"], 940);
    let notice = starter["hosting"]["notice"].as_str().unwrap();
    assert!(notice.contains("dsrl-admin build OfflineBallRun-v0"), "{notice}");

    // A committed identity that differs (one episode's return changed, and so the id): the build fails, naming it.
    let changed = dir.path().join("changed");
    std::fs::create_dir_all(&changed).unwrap();
    let mut record = committed.clone();
    record["version"] = serde_json::Value::from("0".repeat(64));
    std::fs::write(
        changed.join(format!("{TASK}.json")),
        serde_json::to_vec(&record).unwrap(),
    )
    .unwrap();
    let episodes = std::fs::read_to_string(committed_records().join(format!("{TASK}.episodes.csv"))).unwrap();
    let mut lines: Vec<String> = episodes.lines().map(str::to_owned).collect();
    let mut fields: Vec<String> = lines[3].split(',').map(str::to_owned).collect();
    fields[2] = "12345.5".into();
    lines[3] = fields.join(",");
    std::fs::write(changed.join(format!("{TASK}.episodes.csv")), lines.join("\n") + "\n").unwrap();
    let out = build(&root, &changed, 1, &[]).output().unwrap();
    assert!(
        !out.status.success(),
        "a build that differs from its committed identity passed"
    );
    let outcomes: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(outcomes[0]["check"], "differs");
    let details = outcomes[0]["details"].to_string();
    assert!(
        details.contains(&format!("where the committed record has {}", "0".repeat(64))),
        "{details}"
    );
    assert!(details.contains("first differing episode: 2 "), "{details}");
    assert!(String::from_utf8_lossy(&out.stderr).contains("differ from their committed identity"));

    // The build's child killed mid-way (a worker or the machine failing under it): the parent starts it again, it
    // resumes from its last save and ends at the same identity, and the outcome says what happened. This build runs
    // on three workers: the environments' sessions differ from the first build's, the data do not.
    let root = dir.path().join("retried");
    let state = root.join(TASK);
    let parent = build(&root, &committed_records(), 3, &[])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    assert!(
        dsrl_e2e::wait_for(std::time::Duration::from_secs(300), || state
            .join("expert/ckpt-000002/state.json")
            .exists()),
        "the build never saved"
    );
    let child = crate::process_running("build-task", &state).expect("the build's child process");
    assert!(
        !state.join("record").exists(),
        "the build finished before its child could be killed"
    );
    crate::kill_hard(child);
    let out = parent.wait_with_output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let outcomes: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(outcomes[0]["check"], "matches", "{:#}", outcomes[0]);
    assert_eq!(outcomes[0]["version"], version.as_str());
    let retried = outcomes[0]["retried_after"].as_array().unwrap();
    assert_eq!(retried.len(), 1, "{:#}", outcomes[0]);
    assert!(
        retried[0].as_str().unwrap().contains("the build stopped"),
        "{retried:?}"
    );

    // Recorded where a gap record with a measured cost stands: the record keeps the gap's estimate of the whole
    // build, and the gap record goes; recorded again, the estimate stays.
    let records = dir.path().join("records");
    std::fs::create_dir_all(&records).unwrap();
    let gap = serde_json::json!({
        "task": TASK, "state": "partial", "done": 100, "planned": 300, "unit": "steps",
        "cpu_seconds_per_unit": 120.0, "remaining_core_hours": 6.7, "cpu": "a trial's CPU",
    });
    let gap_path = records.join(format!("{TASK}.progress.json"));
    std::fs::write(&gap_path, serde_json::to_vec(&gap).unwrap()).unwrap();
    let read_estimate = || {
        let record: serde_json::Value =
            serde_json::from_slice(&std::fs::read(records.join(format!("{TASK}.json"))).unwrap()).unwrap();
        record["estimate"].clone()
    };
    let expected = serde_json::json!({
        "cpu_seconds_per_unit": 120.0, "unit": "steps", "planned": 300, "core_hours": 10.0, "cpu": "a trial's CPU",
    });
    for (run, check) in [(1, "no committed record"), (2, "matches")] {
        let outcomes = crate::admin_json(build(&root, &records, 1, &["--record"]));
        assert_eq!(outcomes[0]["check"], check, "run {run}: {:#}", outcomes[0]);
        assert_eq!(read_estimate(), expected, "run {run}");
        assert!(!gap_path.exists(), "a recorded build keeps no gap record");
    }
}
