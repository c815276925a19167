//! A worker reports the digest of the `dsrl_sim` package it imported (Health's `version`), so that a scorer built
//! from one tree can tell when its workers play episodes with other Python (`dsrl_leaderboard::scorer_build`).

use std::path::PathBuf;

use crate::support::Worker;

include!("../../../suite/build-support/python_digest.rs");

#[tokio::test]
async fn health_names_the_python_package_the_worker_imported() {
    let source = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("python");
    let digest = python_package_digest(&source.join("dsrl_sim")).unwrap();
    let worker = Worker::start(&["--python-source", source.to_str().unwrap()]).await;
    assert_eq!(
        worker.health().await.version,
        format!(
            "dsrl-sim-worker {} (dsrl_sim {})",
            env!("CARGO_PKG_VERSION"),
            &digest[..12]
        )
    );

    // The same package with one byte more in one file: the worker that imports it says so.
    let copy = std::env::temp_dir().join(format!("dsrl-sim-package-test-{}", std::process::id()));
    let package = copy.join("dsrl_sim");
    std::fs::create_dir_all(&package).unwrap();
    for entry in std::fs::read_dir(source.join("dsrl_sim")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "py") {
            std::fs::copy(&path, package.join(path.file_name().unwrap())).unwrap();
        }
    }
    let tasks = package.join("tasks.py");
    let mut text = std::fs::read_to_string(&tasks).unwrap();
    text.push('\n');
    std::fs::write(&tasks, text).unwrap();
    let changed = python_package_digest(&package).unwrap();
    assert_ne!(changed, digest);
    let worker = Worker::start(&["--python-source", copy.to_str().unwrap()]).await;
    let version = worker.health().await.version;
    std::fs::remove_dir_all(&copy).unwrap();
    assert!(
        version.ends_with(&format!("(dsrl_sim {})", &changed[..12])),
        "{version}"
    );
}
