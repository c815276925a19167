//! The Kubernetes manifests (deploy/k8s) validated offline against the Kubernetes API schemas by
//! `kubernetes-validate` (PyPI, in the test environment), strictly: an unknown or misplaced field fails.

use dsrl_e2e::{python, repo_root};

#[test]
fn kubernetes_manifests_are_valid() {
    let root = repo_root().join("deploy/k8s");
    let mut files = Vec::new();
    for part in ["single", "cluster"] {
        for entry in std::fs::read_dir(root.join(part)).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "yaml") {
                files.push(path);
            }
        }
    }
    files.sort();
    assert!(files.len() >= 7, "{files:?}");
    let out = std::process::Command::new(python().with_file_name("kubernetes-validate"))
        .args(["--strict", "--kubernetes-version", "1.34"])
        .args(&files)
        .output()
        .expect("kubernetes-validate from the test environment (scripts/setup-python.sh)");
    let report = String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{report}");
    // Every part the cluster layout promises is there.
    for resource in [
        "deployment/dsrl-api",
        "poddisruptionbudget/dsrl-api",
        "deployment/dsrl-evaluator",
        "deployment/dsrl-sim-worker",
        "service/dsrl-sim-workers",
        "horizontalpodautoscaler/dsrl-sim-worker",
        "service/dsrl-postgres",
        "cronjob/dsrl-gc",
        "job/dsrl-reference-sweep",
        "persistentvolumeclaim/dsrl-reference-results",
        "job/dsrl-full-builds",
        "persistentvolumeclaim/dsrl-full-builds",
    ] {
        assert!(
            report.contains(&format!("passed for resource {resource}")),
            "{resource}: {report}"
        );
    }
}
