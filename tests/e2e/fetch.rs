//! Fetch: verified downloads, cache hits (also offline), resume after a kill, corruption caught, HDF5 export that
//! DSRL's loader reads, concurrent fetches.

use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

use dsrl_e2e::{run_python, wait_for};

use crate::{Env, sha256_file};

fn flip_byte(path: &Path, offset: u64) {
    let mut f = std::fs::OpenOptions::new().read(true).write(true).open(path).unwrap();
    f.seek(SeekFrom::Start(offset)).unwrap();
    let mut b = [0u8];
    f.read_exact(&mut b).unwrap();
    f.seek(SeekFrom::Start(offset)).unwrap();
    f.write_all(&[b[0] ^ 0xff]).unwrap();
}

#[test]
fn fetch_is_verified_and_later_fetches_hit_the_cache_even_offline() {
    let mut env = Env::new();
    let task = "OfflineAntRun-v0";
    let version = env.ingest_synthetic(task, 5, 20);
    let first = env.cli.run(&["--json", "fetch", task]).ok().json();
    assert_eq!(first["cache_hit"], false);
    assert_eq!(first["version"], version.as_str());
    let path = PathBuf::from(first["path"].as_str().unwrap());
    // One folder per task and version, with DSRL's file name inside.
    assert_eq!(
        path,
        env.path("cache")
            .join(task)
            .join(&version)
            .join("SafetyAntRun-v0-150-5.parquet")
    );
    assert_eq!(sha256_file(&path), version);
    assert_eq!(first["downloaded_bytes"], std::fs::metadata(&path).unwrap().len());
    assert!(path.with_file_name("manifest.json").exists());

    let second = env.cli.run(&["--json", "fetch", task]).ok().json();
    assert_eq!(second["cache_hit"], true);
    assert_eq!(second["downloaded_bytes"], 0);

    // The server is gone: a version id in the cache still resolves; a tag needs the server.
    env.server.kill();
    let offline = env
        .cli
        .run(&["--json", "fetch", task, "--version", &version])
        .ok()
        .json();
    assert_eq!(offline["cache_hit"], true);
    let out = env.cli.run(&["fetch", task]);
    assert_eq!(out.code, 5, "{out:?}");
    assert!(out.stderr.contains("cannot reach the dsrl server"), "{}", out.stderr);
}

#[test]
fn hdf5_export_loads_like_dsrl_and_equals_the_parquet() {
    let env = Env::new();
    let task = "OfflineDroneRun-v0";
    let version = env.ingest_synthetic(task, 7, 21);
    let out = env.cli.run(&["--json", "fetch", task, "--format", "hdf5"]).ok().json();
    assert_eq!(out["format"], "hdf5");
    // The server's export, made once on the server and downloaded (verified against its sha256), not converted here.
    assert_eq!(out["converted"], false, "{out}");
    let exports = |outcome: &str| {
        let text = crate::leaderboard::reqwest_text(&format!("{}/metrics", env.server.url));
        let key = format!("dsrl_hdf5_exports_total{{outcome=\"{outcome}\"}} ");
        text.lines()
            .find_map(|l| l.strip_prefix(key.as_str()).map(|v| v.trim().parse::<f64>().unwrap()))
            .unwrap_or(0.0)
    };
    assert_eq!(exports("computed"), 1.0);
    let other_cache = env.dir.path().join("other-cache");
    let other = env
        .cli
        .command(&["--json", "fetch", task, "--format", "hdf5"])
        .env("DSRL_DATASET_DIR", &other_cache)
        .output()
        .unwrap();
    assert!(other.status.success());
    assert_eq!(
        (exports("computed"), exports("cached")),
        (1.0, 1.0),
        "a second client gets the stored export"
    );
    let h5 = out["path"].as_str().unwrap().to_owned();
    assert!(h5.ends_with(&format!("{version}/SafetyDroneRun-v0-140-7.hdf5")), "{h5}");
    // Only the export came down: the Parquet file is not needed for it.
    assert_eq!(out["parquet_path"], serde_json::Value::Null, "{out}");
    assert_eq!(
        out["downloaded_bytes"].as_u64(),
        std::fs::metadata(&h5).ok().map(|m| m.len()),
        "{out}"
    );
    let plain = env.cli.run(&["--json", "fetch", task]).ok().json();
    let parquet = plain["path"].as_str().unwrap().to_owned();
    assert_eq!(plain["parquet_path"].as_str(), Some(parquet.as_str()));
    let loaded: serde_json::Value =
        serde_json::from_str(&run_python("dsrl_get_dataset.py", &[&h5, &parquet, "17", "4"])).unwrap();
    let manifest = env.cli.run(&["--json", "show", task]).ok().json();
    assert_eq!(loaded["transitions"], manifest["transitions"]);
    assert_eq!(loaded["episodes"], manifest["episodes"]);
    assert_eq!(loaded["dtypes"]["terminals"], "bool");
    assert_eq!(loaded["dtypes"]["observations"], "float32");
    // The episode index's returns are exactly NumPy's float32 sums over the same slices.
    let ours: Vec<f32> = manifest["episode_index"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["reward_return"].as_f64().unwrap() as f32)
        .collect();
    let numpy: Vec<f32> = loaded["reward_returns"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap() as f32)
        .collect();
    assert_eq!(ours, numpy);
    // The HDF5 file is now in the cache too.
    let again = env.cli.run(&["--json", "fetch", task, "--format", "hdf5"]).ok().json();
    assert_eq!(
        (again["cache_hit"].as_bool(), again["converted"].as_bool()),
        (Some(true), Some(false))
    );
}

/// Starts a rate-limited fetch and SIGKILLs it once the partial file has `at_least` bytes.
fn kill_mid_download(env: &Env, task: &str, part: &Path, at_least: u64) {
    let mut child = env
        .cli
        .command(&["fetch", task, "--limit-rate", "1M"])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let grew = wait_for(Duration::from_secs(60), || {
        std::fs::metadata(part).is_ok_and(|m| m.len() >= at_least)
    });
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(grew, "the download never reached {at_least} bytes");
}

fn big_version(env: &Env) -> (String, u64, PathBuf) {
    // MetaDrive rows are ~2 KB: 4 episodes are a ~6 MB file, several seconds at 1 MB/s.
    let task = "OfflineMetadrive-easysparse-v0";
    let version = env.ingest_synthetic(task, 4, 22);
    let manifest = env.cli.run(&["--json", "show", task]).ok().json();
    let size = manifest["byte_size"].as_u64().unwrap();
    let file_name = manifest["file_name"].as_str().unwrap();
    let part = env
        .path("cache")
        .join(task)
        .join(&version)
        .join(format!("{file_name}.part"));
    (version, size, part)
}

#[test]
fn a_killed_download_resumes_where_it_stopped() {
    let env = Env::new();
    let task = "OfflineMetadrive-easysparse-v0";
    let (version, size, part) = big_version(&env);
    assert!(size > 4 << 20, "{size}");
    kill_mid_download(&env, task, &part, 1 << 20);
    let final_path = part.with_extension("");
    assert!(
        !final_path.exists(),
        "a partial download must never take the final name"
    );
    let partial = std::fs::metadata(&part).unwrap().len();
    assert!(partial < size);

    let out = env.cli.run(&["--json", "fetch", task]).ok().json();
    let resumed_from = out["resumed_from"].as_u64().expect("the fetch resumed");
    assert!(
        resumed_from >= 1 << 20 && resumed_from <= partial,
        "{resumed_from} vs {partial}"
    );
    assert_eq!(out["downloaded_bytes"].as_u64().unwrap(), size - resumed_from);
    assert_eq!(sha256_file(&final_path), version);
    assert!(!part.exists());
    assert_eq!(env.cli.run(&["verify"]).code, 0);
}

#[test]
fn a_corrupted_partial_download_is_caught_and_discarded() {
    let env = Env::new();
    let task = "OfflineMetadrive-easysparse-v0";
    let (version, _, part) = big_version(&env);
    kill_mid_download(&env, task, &part, 1 << 20);
    flip_byte(&part, 1000);
    let out = env.cli.run(&["fetch", task]);
    assert_eq!(out.code, 3, "{out:?}");
    assert!(out.stderr.contains("not to the version id"), "{}", out.stderr);
    assert!(!part.exists(), "the corrupt partial file is removed");
    assert!(!part.with_extension("").exists());
    let out = env.cli.run(&["--json", "fetch", task]).ok().json();
    assert_eq!(out["resumed_from"], serde_json::Value::Null);
    assert_eq!(sha256_file(Path::new(out["path"].as_str().unwrap())), version);
}

#[test]
fn verify_finds_and_removes_corrupt_files_and_fetch_repairs_them() {
    let env = Env::new();
    let task = "OfflineBallCircle-v0";
    env.ingest_synthetic(task, 6, 23);
    let plain = env.cli.run(&["--json", "fetch", task]).ok().json();
    let out = env.cli.run(&["--json", "fetch", task, "--format", "hdf5"]).ok().json();
    let parquet = PathBuf::from(plain["path"].as_str().unwrap());
    // The Parquet file already in the cache is named beside the export.
    assert_eq!(out["parquet_path"], plain["path"], "{out}");
    let h5 = PathBuf::from(out["path"].as_str().unwrap());
    let clean = env.cli.run(&["--json", "verify"]).ok().json();
    assert_eq!(clean["files"].as_array().unwrap().len(), 2);

    flip_byte(&parquet, 200);
    flip_byte(&h5, std::fs::metadata(&h5).unwrap().len() - 10);
    let out = env.cli.run(&["--json", "verify"]);
    assert_eq!(out.code, 3, "{out:?}");
    let report = out.json();
    let corrupt: Vec<&str> = report["files"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|f| f["status"] == "corrupt")
        .map(|f| f["path"].as_str().unwrap())
        .collect();
    assert_eq!(corrupt.len(), 2, "{report}");
    assert!(!parquet.exists() && !h5.exists(), "corrupt files are removed");
    assert_eq!(env.cli.run(&["verify"]).code, 0, "nothing corrupt is left");

    let cached = || {
        env.cli.run(&["--json", "verify"]).ok().json()["files"]
            .as_array()
            .unwrap()
            .len()
    };
    let out = env.cli.run(&["--json", "fetch", task, "--format", "hdf5"]).ok().json();
    assert_eq!(out["cache_hit"], false);
    assert!(out["downloaded_bytes"].as_u64().unwrap() > 0);
    assert_eq!(cached(), 1, "the export alone comes down for --format hdf5");
    env.cli.run(&["fetch", task]).ok();
    assert_eq!(cached(), 2);
}

#[test]
fn concurrent_fetches_of_one_version_take_turns() {
    let env = Env::new();
    let task = "OfflineCarCircle-v0";
    let version = env.ingest_synthetic(task, 30, 24);
    let children: Vec<_> = (0..4)
        .map(|_| {
            env.cli
                .command(&["--json", "fetch", task])
                .stdout(std::process::Stdio::piped())
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    let outcomes: Vec<serde_json::Value> = children
        .into_iter()
        .map(|c| {
            let out = c.wait_with_output().unwrap();
            assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
            serde_json::from_slice(&out.stdout).unwrap()
        })
        .collect();
    let downloads = outcomes.iter().filter(|o| o["cache_hit"] == false).count();
    assert_eq!(
        downloads, 1,
        "exactly one process downloads; the others find it complete: {outcomes:?}"
    );
    let path = Path::new(outcomes[0]["path"].as_str().unwrap());
    assert_eq!(sha256_file(path), version);
    let entries: Vec<_> = std::fs::read_dir(path.parent().unwrap())
        .unwrap()
        .flatten()
        .map(|e| e.file_name())
        .collect();
    assert!(
        !entries.iter().any(|n| n.to_string_lossy().ends_with(".part")),
        "{entries:?}"
    );
}
