//! Starter datasets: ingested at start-up when missing, with their recipe provenance; never moving `latest` back.

use crate::{Env, s};

#[test]
fn starter_datasets_load_once_and_never_move_latest_back() {
    let dir = tempfile::tempdir().unwrap();
    let starter = dir.path().join("starter");
    let task = "OfflineBallRun-v0";
    std::fs::create_dir_all(starter.join(task)).unwrap();
    let file = starter.join(task).join("SafetyBallRun-v0-80-5.parquet");
    let made = dsrl_e2e::make_dataset(task, 5, 50, &file);
    let provenance = serde_json::json!({
        "kind": "recipe", "recipe": "data/recipes/test.toml", "seeds": [50], "code_version": "test",
        "details": {"budget_steps": 1000}
    });
    std::fs::write(format!("{}.provenance.json", file.display()), provenance.to_string()).unwrap();

    let mut env = Env::with(&["--starter-datasets", s(&starter)], &[]);
    let manifest = env.cli.run(&["--json", "show", task]).ok().json();
    assert_eq!(manifest["version"], made.version.as_str());
    assert_eq!(manifest["provenance"]["kind"], "recipe");
    assert_eq!(manifest["provenance"]["seeds"], serde_json::json!([50]));

    env.restart();
    let list = env.cli.run(&["--json", "list"]).ok().json();
    let ball = list
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["id"] == task)
        .unwrap()
        .clone();
    assert_eq!(
        ball["versions"].as_array().unwrap().len(),
        1,
        "a restart does not duplicate"
    );

    let newer = env.ingest_synthetic(task, 6, 51);
    env.restart();
    let shown = env.cli.run(&["--json", "show", task]).ok().json();
    assert_eq!(
        shown["version"],
        newer.as_str(),
        "latest stays on the newer upload after a restart"
    );
}
