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

/// A starter committed in parts (a dataset larger than one committed file may be) is joined back into one version:
/// the canonical file's, with the provenance named after the whole.
#[test]
fn a_starter_committed_in_parts_loads_as_the_one_version_of_the_whole() {
    use dsrl_suite::convert::{part_file_name, split_compact};
    let dir = tempfile::tempdir().unwrap();
    let starter = dir.path().join("starter");
    let task = "OfflineMetadrive-easydense-v0";
    std::fs::create_dir_all(starter.join(task)).unwrap();
    let canonical = dir.path().join("canonical.parquet");
    let made = dsrl_e2e::make_dataset(task, 7, 52, &canonical);
    let name = "SafeMetaDrive-easydense-85-7.parquet";
    let parts: Vec<_> = (1..=3)
        .map(|i| starter.join(task).join(part_file_name(name, i, 3)))
        .collect();
    let catalog = dsrl_suite::Catalog::embedded().unwrap();
    split_compact(
        catalog.get(task).unwrap(),
        dsrl_suite::ObservationSpace::Simulator,
        &canonical,
        &made.episode_index,
        &parts,
    )
    .unwrap();
    let provenance = serde_json::json!({
        "kind": "recipe", "recipe": "data/recipes/test.toml", "seeds": [52], "code_version": "test",
        "details": {"episodes_kept": 7}
    });
    std::fs::write(
        starter.join(task).join(format!("{name}.provenance.json")),
        provenance.to_string(),
    )
    .unwrap();

    let env = Env::with(&["--starter-datasets", s(&starter)], &[]);
    let manifest = env.cli.run(&["--json", "show", task]).ok().json();
    assert_eq!(manifest["version"], made.version.as_str(), "{manifest}");
    assert_eq!(manifest["episodes"], 7);
    assert_eq!(manifest["provenance"]["seeds"], serde_json::json!([52]));
}

/// What the README's first command serves: every file under data/starter (within the size budgets, one per task
/// or a recorded gap), validated and ingested at start-up by `env`'s server, with its recipe provenance.
pub(crate) fn every_committed_starter_loads_with_its_recipe_provenance(env: &Env) {
    let starter = dsrl_e2e::repo_root().join("data/starter");
    let mut expected: Vec<(String, u64)> = Vec::new();
    for task in std::fs::read_dir(&starter).unwrap() {
        let task = task.unwrap();
        // Beside the task folders: versions.csv, the ids the server gives them (checked in hosted.rs).
        if !task.path().is_dir() {
            continue;
        }
        for file in std::fs::read_dir(task.path()).unwrap() {
            let name = file.unwrap().file_name().into_string().unwrap();
            if name.ends_with(".parquet") {
                let size = std::fs::metadata(task.path().join(&name)).unwrap().len();
                assert!(size <= 8_000_000, "{name} is {size} bytes, over the 8 MB per file");
                // A dataset in parts counts once, under the name its parts share.
                let name = match dsrl_suite::convert::parse_part_file_name(&name) {
                    Some((_, index, _)) if index > 1 => continue,
                    Some((whole, _, _)) => whole,
                    None => name,
                };
                // DSRL's naming: <prefix>-<cost cap>-<trajectories>.
                let stem = name.strip_suffix(".parquet").unwrap();
                let episodes = stem.rsplit('-').next().unwrap().parse().unwrap();
                expected.push((task.file_name().into_string().unwrap(), episodes));
            }
        }
    }
    // One starter per catalog task (a task without one is a `hosted` gap in data/starter_gaps.csv).
    let catalog = dsrl_suite::Catalog::embedded().unwrap();
    let missing: Vec<&str> = catalog
        .tasks()
        .iter()
        .map(|t| t.id.as_str())
        .filter(|id| !expected.iter().any(|(task, _)| task == id))
        .collect();
    let recorded = std::fs::read_to_string(dsrl_e2e::repo_root().join("data/starter_gaps.csv")).unwrap();
    for id in &missing {
        assert!(
            recorded.contains(&format!("{id},hosted,")),
            "{id} has no starter and no recorded gap"
        );
    }
    assert_eq!(expected.len() + missing.len(), 38, "{expected:?}");
    let total: u64 = walk_bytes(&starter);
    // Each committed file at most 8 MB, all of them at most 250 MB (the repository's budget for data).
    assert!(
        total <= 250_000_000,
        "starter data is {total} bytes, over the 250 MB budget"
    );

    for (task, episodes) in &expected {
        let manifest = env.cli.run(&["--json", "show", task]).ok().json();
        assert_eq!(manifest["episodes"], *episodes, "{task}");
        assert_eq!(manifest["provenance"]["kind"], "recipe", "{task}");
        assert_eq!(
            manifest["provenance"]["recipe"],
            format!("data/recipes/{task}.toml"),
            "{task}"
        );
    }
}

fn walk_bytes(dir: &std::path::Path) -> u64 {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| {
            let e = e.unwrap();
            if e.file_type().unwrap().is_dir() {
                walk_bytes(&e.path())
            } else {
                e.metadata().unwrap().len()
            }
        })
        .sum()
}

/// `dsrl-admin compact` rewrites a starter cut before the compact form (the full canonical layout) row for row:
/// smaller, the same version id once the server ingests it, in parts and back; a wrong task changes nothing.
#[test]
fn dsrl_admin_compact_rewrites_a_starter_smaller_under_the_same_version() {
    let dir = tempfile::tempdir().unwrap();
    let starter = dir.path().join("starter");
    let task = "OfflineBallRun-v0";
    let folder = starter.join(task);
    std::fs::create_dir_all(&folder).unwrap();
    let name = "SafetyBallRun-v0-80-12.parquet";
    let file = folder.join(name);
    let made = dsrl_e2e::make_dataset(task, 12, 53, &file);
    let full_size = std::fs::metadata(&file).unwrap().len();
    let provenance = serde_json::json!({
        "kind": "recipe", "recipe": "data/recipes/test.toml", "seeds": [53], "code_version": "test",
        "details": {"episodes_kept": 12}
    });
    std::fs::write(folder.join(format!("{name}.provenance.json")), provenance.to_string()).unwrap();
    let compact = |args: &[&str]| {
        let mut cmd = std::process::Command::new(dsrl_e2e::bin("dsrl-admin"));
        cmd.args(["compact", "--json", "--task"]).args(args);
        cmd
    };

    // A wrong task: refused with the reason, the file untouched and no scratch left behind.
    let before = crate::sha256_file(&file);
    let out = compact(&["OfflineDroneRun-v0", s(&file)]).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("OfflineDroneRun-v0"), "{err}");
    assert_eq!(crate::sha256_file(&file), before);
    assert_eq!(
        std::fs::read_dir(&folder).unwrap().count(),
        2,
        "the file and its provenance only"
    );

    // Into two parts in another folder, the provenance copied along.
    let split = dir.path().join("split");
    let report = crate::admin_json(compact(&[task, "--parts", "2", "--out", s(&split), s(&file)]));
    assert_eq!(report["version"], made.version.as_str());
    let parts: Vec<std::path::PathBuf> = (1..=2)
        .map(|i| split.join(dsrl_suite::convert::part_file_name(name, i, 2)))
        .collect();
    assert!(parts.iter().all(|p| p.is_file()), "{report}");
    assert!(split.join(format!("{name}.provenance.json")).is_file());
    assert_eq!(crate::sha256_file(&file), before, "--out leaves the input alone");

    // The parts back into one file, in place: the parts are replaced.
    let parts_args: Vec<&str> = parts.iter().map(|p| s(p)).collect();
    let joined = crate::admin_json(compact(&[&[task][..], &parts_args].concat()));
    assert_eq!(joined["version"], made.version.as_str());
    assert!(split.join(name).is_file() && parts.iter().all(|p| !p.exists()));

    // In place on the full-form file: smaller, and the server hosts it under the same version.
    let report = crate::admin_json(compact(&[task, s(&file)]));
    assert_eq!(report["version"], made.version.as_str());
    let compact_size = std::fs::metadata(&file).unwrap().len();
    assert_eq!(report["bytes_before"], full_size);
    assert_eq!(report["bytes_after"], compact_size);
    assert!(compact_size < full_size, "{compact_size} >= {full_size}");
    assert_eq!(std::fs::read_dir(&folder).unwrap().count(), 2, "no scratch left behind");
    let env = Env::with(&["--starter-datasets", s(&starter)], &[]);
    let manifest = env.cli.run(&["--json", "show", task]).ok().json();
    assert_eq!(manifest["version"], made.version.as_str(), "{manifest}");
    assert_eq!(manifest["episodes"], 12);
    assert_eq!(manifest["provenance"]["seeds"], serde_json::json!([53]));
}
