//! `dsrl-admin collect` end to end: a small MetaDrive IDM sweep on real workers, killed mid-run and resumed, gives
//! the same dataset as an uninterrupted run, and is ingested with its recipe provenance. A sweep that plays several
//! settings per session (environments switch the driver on reset) drives each setting as fresh sessions do, and
//! replays an unfinished block whole when resumed.

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use crate::Env;

const TASK: &str = "OfflineMetadrive-easysparse-v0";

/// The task's recipe cut down to 2 settings of 2 episodes.
fn tiny_recipe(dir: &Path) -> std::path::PathBuf {
    let text = std::fs::read_to_string(dsrl_e2e::repo_root().join(format!("data/recipes/{TASK}.toml"))).unwrap();
    let text = text
        .replace(
            "{ start = 0.0, stop = 6.0, step = 0.6 }",
            "{ start = 1.2, stop = 1.3, step = 0.6 }",
        )
        .replace("[5, 9, 13, 17, 21]", "[13, 21]")
        .replace("episodes_per_setting = 20", "episodes_per_setting = 2");
    assert!(
        text.contains("[13, 21]") && text.contains("stop = 1.3"),
        "the recipe's layout changed"
    );
    let path = dir.join("tiny.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// `dsrl-admin collect` on one worker, two environments per session unless `extra` says otherwise.
fn collect(recipe: &Path, state: &Path, extra: &[&str]) -> Command {
    let envs: &[&str] = if extra.contains(&"--envs-per-session") {
        &[]
    } else {
        &["--envs-per-session", "2"]
    };
    crate::admin_collect(TASK, recipe, state, &[&["--workers", "1"], envs, extra].concat())
}

#[test]
fn a_killed_collection_resumes_to_the_same_dataset_ingests_with_provenance_and_blocks_play_as_fresh_sessions() {
    let env = Env::new();
    let recipe = tiny_recipe(env.dir.path());

    // Uninterrupted reference run.
    let reference = crate::admin_json(collect(&recipe, &env.path("reference"), &[]));
    assert_eq!(reference["episodes"], 4);
    let version = reference["version"].as_str().unwrap().to_owned();

    // Killed once the first setting is saved, then resumed and ingested.
    let state = env.path("killed");
    crate::kill_once_saved(
        collect(&recipe, &state, &[]),
        &state.join("settings/000.parquet"),
        &state.join("settings/001.parquet"),
    );
    let token = env.server.token();
    let resumed = crate::admin_json(collect(
        &recipe,
        &state,
        &["--server", &env.server.url, "--token", &token, "--tag", "idm-tiny"],
    ));
    assert_eq!(resumed["version"], version.as_str(), "resuming changed the dataset");
    assert_eq!(resumed["ingested"]["created"], true);

    let manifest = crate::get_json(&format!("{}/v1/datasets/{TASK}/versions/idm-tiny", env.server.url));
    assert_eq!(manifest["version"], version.as_str());
    let provenance = &manifest["provenance"];
    assert_eq!(provenance["kind"], "recipe");
    assert_eq!(provenance["seeds"], serde_json::json!([0]));
    assert_eq!(provenance["details"]["episodes_collected"], 4);
    assert_eq!(manifest["episodes"], 4);
    // The code that made it: the commit this clone's dsrl-admin was built from (pipeline/build.rs).
    let head = std::process::Command::new("git")
        .args(["rev-parse", "--short=12", "HEAD"])
        .current_dir(dsrl_e2e::repo_root())
        .output()
        .unwrap();
    let head = String::from_utf8(head.stdout).unwrap();
    let code_version = provenance["code_version"].as_str().unwrap();
    assert!(
        code_version.starts_with(&format!(
            "dsrl-pipeline {} (git {}",
            env!("CARGO_PKG_VERSION"),
            head.trim()
        )),
        "{code_version}"
    );
    // Its workers ran this tree's simulator Python, so the run noted no other (which would mark the code
    // `-modified`: pipeline/src/build.rs, `code_version`).
    assert!(!state.join("other-simulator-python").exists());

    // A starter-sized cut of the finished run reuses its settings: nothing is simulated again.
    let starter = env.path("starter");
    let started = std::time::Instant::now();
    let cut = crate::admin_json(collect(
        &recipe,
        &state,
        &["--max-episodes", "2", "--out", starter.to_str().unwrap()],
    ));
    assert!(started.elapsed() < Duration::from_secs(20), "the cut simulated again");
    assert_eq!(cut["episodes"], 2);
    assert_eq!(cut["provenance"]["details"]["thinned_to"], 2);
    let file = cut["file"].as_str().unwrap();
    assert!(
        file.starts_with(starter.to_str().unwrap()) && file.ends_with("-85-2.parquet"),
        "{file}"
    );
    assert!(Path::new(&format!("{file}.provenance.json")).exists());

    // The same run cut into two compact parts (a starter over one file's budget): the version is the whole's.
    let parts_dir = env.path("starter-parts");
    let cut = crate::admin_json(collect(
        &recipe,
        &state,
        &["--compact", "--parts", "2", "--out", parts_dir.to_str().unwrap()],
    ));
    assert_eq!(cut["version"], version.as_str());
    let files: Vec<&str> = cut["files"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_str().unwrap())
        .collect();
    assert_eq!(files.len(), 2, "{cut}");
    assert!(files[0].ends_with("-85-4.part-1-of-2.parquet") && files[1].ends_with("-85-4.part-2-of-2.parquet"));
    assert!(files.iter().all(|f| Path::new(f).exists()));
    assert!(
        !Path::new(cut["file"].as_str().unwrap()).exists(),
        "only the parts are written"
    );
    assert!(Path::new(&format!("{}.provenance.json", cut["file"].as_str().unwrap())).exists());

    // The same settings played as one block per session (below), against the uninterrupted run's fresh sessions.
    a_block_of_settings_per_session_drives_each_as_fresh_sessions_do_and_resumes_whole(
        &recipe,
        &env.path("reference"),
        &env.path("block"),
    );
}

/// Each episode's length in a stored setting (`<state>/settings/NNN.parquet`).
fn episode_lengths(state: &Path, setting: usize) -> Vec<usize> {
    let file = std::fs::File::open(state.join(format!("settings/{setting:03}.parquet"))).unwrap();
    let mut lengths = vec![0];
    for chunk in dsrl_suite::parquet_file::ParquetTransitions::open(file).unwrap() {
        let chunk = chunk.unwrap();
        for i in 0..chunk.len() {
            *lengths.last_mut().unwrap() += 1;
            if chunk.is_done(i) {
                lengths.push(0);
            }
        }
    }
    assert_eq!(lengths.pop(), Some(0), "a stored setting ends mid-episode");
    lengths
}

/// A sweep that plays a block of settings per session (environments switch the driver on reset), against `fresh`, a
/// finished run of the same recipe in fresh sessions: each setting is driven as fresh sessions drive it, and an
/// unfinished block is replayed whole when resumed.
fn a_block_of_settings_per_session_drives_each_as_fresh_sessions_do_and_resumes_whole(
    recipe: &Path,
    fresh: &Path,
    block: &Path,
) {
    let (recipe, fresh, block) = (recipe.to_owned(), fresh.to_owned(), block.to_owned());
    let blocked = crate::admin_json(collect(&recipe, &block, &["--settings-per-session", "2"]));
    assert_eq!(blocked["episodes"], 4);
    assert_eq!(blocked["provenance"]["details"]["settings_per_session"], 2);

    // Two environments play the block's four episodes; the second setting's are driven after a switch on reset.
    // Their lengths match fresh sessions' at that setting (a reused environment does not replay a fresh one to the
    // last bit, so not exactly), and differ from the first setting's, so the switch took effect.
    let (fast_fresh, slow_fresh) = (episode_lengths(&fresh, 1), episode_lengths(&fresh, 0));
    let fast_block = episode_lengths(&block, 1);
    for (a, b) in fast_block.iter().zip(&fast_fresh) {
        assert!(
            a.abs_diff(*b) * 50 <= *b,
            "21 km/h after a switch: {fast_block:?}, fresh {fast_fresh:?}"
        );
    }
    for (a, b) in slow_fresh.iter().zip(&fast_fresh) {
        assert!(
            a.abs_diff(*b) * 10 > *b,
            "13 and 21 km/h should differ: {slow_fresh:?}, {fast_fresh:?}"
        );
    }

    // A block with a setting missing is played again whole: the same dataset as the uninterrupted run.
    std::fs::remove_file(block.join("settings/001.parquet")).unwrap();
    let resumed = crate::admin_json(collect(&recipe, &block, &["--settings-per-session", "2"]));
    assert_eq!(
        resumed["version"], blocked["version"],
        "replaying the block changed the dataset"
    );
    assert_eq!(episode_lengths(&block, 1), fast_block);
}

/// Where every episode's environment is known in advance, the worker's driver plays whole episodes; stepped through
/// the protocol instead (`--step-episodes`), the same layout gives the same dataset. CI proves the driver's episodes
/// equal stepped ones at the worker (`sim/tests/it/controller.rs`); this runs it through `dsrl-admin` in two layouts.
#[test]
#[ignore = "long check (scripts/long-checks.sh): sim/tests/it/controller.rs proves driven == stepped in CI"]
fn driven_and_stepped_collections_give_the_same_dataset() {
    let dir = tempfile::tempdir().unwrap();
    let recipe = tiny_recipe(dir.path());
    let fresh = dir.path().join("fresh");
    // Two layouts: fresh sessions (both episodes of a setting dealt at once to two environments), and a block on one
    // environment (four episodes one after another, the driver switched on reset).
    let fresh_stepped = crate::admin_json(collect(
        &recipe,
        &dir.path().join("fresh-stepped"),
        &["--step-episodes"],
    ));
    let fresh_driven = crate::admin_json(collect(&recipe, &fresh, &[]));
    assert_eq!(
        fresh_stepped["version"], fresh_driven["version"],
        "driven and stepped episodes differ"
    );
    let one_env = ["--settings-per-session", "2", "--envs-per-session", "1"];
    let driven = crate::admin_json(collect(&recipe, &dir.path().join("one-env"), &one_env));
    let stepped = crate::admin_json(collect(
        &recipe,
        &dir.path().join("one-env-stepped"),
        &[&one_env[..], &["--step-episodes"]].concat(),
    ));
    assert_eq!(driven["episodes"], 4);
    assert_eq!(
        stepped["version"], driven["version"],
        "driven and stepped episodes differ"
    );
}

#[test]
fn without_recipe_flag_the_recipe_is_the_current_directorys() {
    // The default is `data/recipes/<task>.toml` under the working directory, not the clone the binary was built
    // in: a folder with no recipes is refused, naming the path, and a folder's own recipe is the one read (here
    // one of another task, which is refused before anything is simulated).
    let dir = tempfile::tempdir().unwrap();
    let run = |cwd: &Path| {
        let out = crate::admin_collect_default_recipe(TASK, &dir.path().join("state"))
            .current_dir(cwd)
            .output()
            .unwrap();
        assert!(!out.status.success());
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let refused = run(dir.path());
    assert!(
        refused.contains(&format!("no recipe at data/recipes/{TASK}.toml")) && refused.contains("--recipe"),
        "{refused}"
    );

    let recipes = dir.path().join("clone/data/recipes");
    std::fs::create_dir_all(&recipes).unwrap();
    let other =
        std::fs::read_to_string(dsrl_e2e::repo_root().join("data/recipes/OfflineMetadrive-easymean-v0.toml")).unwrap();
    std::fs::write(recipes.join(format!("{TASK}.toml")), other).unwrap();
    let read = run(&dir.path().join("clone"));
    assert!(
        read.contains(&format!("is the recipe of OfflineMetadrive-easymean-v0, not {TASK}")),
        "{read}"
    );
    assert!(!dir.path().join("state").exists(), "nothing ran");
}
